# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The fleet report behind playbooks/status.yml."""

from __future__ import annotations

DOCUMENTATION = r"""
name: isaac_sim_fleet_report
short_description: Fold the isaac_sim_info results of many hosts into one fleet report
version_added: "0.2.0"
description:
  - "Takes C({host: result}) of M(isaacsim.fleet.isaac_sim_info) and the hosts that were asked, and returns
    a fleet summary (hosts, instances, running, ready, failed, stray) and the hosts with their instances,
    each with display fields (uptime, GPU text, primary URL, the URL to embed)."
  - A host without a result, or with a failed one, is reported unreachable with the reason.
  - Keyword options go as C(name=value).
positional: _input, targets, generated_at
options:
  _input:
    description: "C({host: isaac_sim_info result})."
    type: dict
    required: true
  targets:
    description: Every host the status was asked of, in display order.
    type: list
    elements: str
    required: true
  generated_at:
    description: Time stamp shown in the report.
    type: str
    default: ""
  mirrors:
    description:
      - "C({mirror host: isaac_sim_mirror_info result}) of the fleet's registry mirrors: the report gets C(mirrors),
        each serving or not (and why) and what its storage holds, and the table a line for each."
    type: dict
    default: {}
  front_doors:
    description:
      - "C({front door host: {door: its front-door.json, relay: the state of its relay's unit}}) of the fleet's
        front doors: the report gets C(front_doors), each with its address, its certificate's expiry (and days
        left), its relay's state and whether it is healthy; each instance behind one its C(entrance); the table a
        line for each door and the entrance in an instance's URL column."
    type: dict
    default: {}
"""

EXAMPLES = r"""
report: "{{ results | isaacsim.fleet.isaac_sim_fleet_report(ansible_play_hosts_all, now(utc=true).isoformat()) }}"
"""

RETURN = r"""
_value:
  description: The report (C(generated_at), C(summary), C(hosts)).
  type: dict
"""


def isaac_sim_fleet_report(*args, **kwargs):
    # on use, not at load: Ansible loads every filter file here to find one (docs/docsite/rst/contributing.rst, Layout)
    from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.fleet_report import build

    return build(*args, **kwargs)


class FilterModule:
    def filters(self):
        return {"isaac_sim_fleet_report": isaac_sim_fleet_report}
