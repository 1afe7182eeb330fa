# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The collection's host layout, for the role's variables and templates."""

from __future__ import annotations

DOCUMENTATION = r"""
name: isaac_sim_layout
short_description: The host layout of isaacsim.fleet (directories, unit and container names)
version_added: "0.3.0"
description:
  - Returns the paths and names the collection uses on a host, from its one definition in module_utils,
    so playbooks and templates never spell them out.
positional: _input
options:
  _input:
    description: The data root of the instances (C(isaac_sim_data_root)).
    type: path
    required: true
"""

EXAMPLES = r"""
config_dir: "{{ (isaac_sim_data_root | isaacsim.fleet.isaac_sim_layout).config_dir }}"
"""

RETURN = r"""
_value:
  description: C(config_dir), C(unit_dir), C(libexec_dir), C(lib_dir), C(run_dir), C(data_root),
    C(unit_template), C(target), C(container_prefix), C(label_instance).
  type: dict
"""


def isaac_sim_layout(data_root):
    # on use, not at load: Ansible loads every filter file here to find one (docs/docsite/rst/contributing.rst, Layout)
    from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout

    return layout.as_dict(str(data_root))


class FilterModule:
    def filters(self):
        return {"isaac_sim_layout": isaac_sim_layout}
