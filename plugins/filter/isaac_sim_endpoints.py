# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Stream addresses of planned instances."""

from __future__ import annotations

DOCUMENTATION = r"""
name: isaac_sim_endpoints
short_description: One line per instance with its GPU and stream addresses
version_added: "0.1.0"
description:
  - For a plan returned by M(isaacsim.fleet.isaac_sim_plan), lists each instance with the addresses
    its release serves, on the given host address.
positional: _input, host
options:
  _input:
    description: The plan.
    type: dict
    required: true
  host:
    description: Address clients use for this host.
    type: str
    required: true
"""

EXAMPLES = r"""
msg: "{{ plan | isaacsim.fleet.isaac_sim_endpoints('10.0.0.5') }}"
"""

RETURN = r"""
_value:
  description: One line per instance.
  type: list
  elements: str
"""


def isaac_sim_endpoints(*args, **kwargs):
    # on use, not at load: Ansible loads every filter file here to find one (docs/docsite/rst/contributing.rst, Layout)
    from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.endpoints import summary_lines

    return summary_lines(*args, **kwargs)


class FilterModule:
    def filters(self):
        return {"isaac_sim_endpoints": isaac_sim_endpoints}
