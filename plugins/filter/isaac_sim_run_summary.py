# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""A test run's result as lines for a person."""

from __future__ import annotations

DOCUMENTATION = r"""
name: isaac_sim_run_summary
short_description: A test run's verdict and one row per service (exit code, restarts, CPU and memory peaks)
version_added: "0.3.0"
description:
  - Turns the result of M(isaacsim.fleet.isaac_sim_experience) into lines for the play's output.
positional: _input
options:
  _input:
    description: The module's result.
    type: dict
    required: true
"""

EXAMPLES = r"""
msg: "{{ run | isaacsim.fleet.isaac_sim_run_summary }}"
"""

RETURN = r"""
_value:
  description: The verdict line, a header and one line per service.
  type: list
  elements: str
"""


def isaac_sim_run_summary(*args, **kwargs):
    # on use, not at load: Ansible loads every filter file here to find one (docs/docsite/rst/contributing.rst, Layout)
    from ansible_collections.isaacsim.fleet.plugins.module_utils.runs.testrun import summary_lines

    return summary_lines(*args, **kwargs)


class FilterModule:
    def filters(self):
        return {"isaac_sim_run_summary": isaac_sim_run_summary}
