# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The compact status table of playbooks/status.yml."""

from __future__ import annotations

DOCUMENTATION = r"""
name: isaac_sim_status_table
short_description: The fleet report as an aligned text table
version_added: "0.2.0"
description:
  - One line per instance (host, instance, state, ready, uptime, restarts, GPU, URL) and a summary line,
    from the report of P(isaacsim.fleet.isaac_sim_fleet_report#filter).
positional: _input
options:
  _input:
    description: The fleet report.
    type: dict
    required: true
"""

EXAMPLES = r"""
msg: "{{ report | isaacsim.fleet.isaac_sim_status_table }}"
"""

RETURN = r"""
_value:
  description: Table lines.
  type: list
  elements: str
"""


def isaac_sim_status_table(*args, **kwargs):
    # on use, not at load: Ansible loads every filter file here to find one (docs/docsite/rst/contributing.rst, Layout)
    from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.fleet_report import table

    return table(*args, **kwargs)


class FilterModule:
    def filters(self):
        return {"isaac_sim_status_table": isaac_sim_status_table}
