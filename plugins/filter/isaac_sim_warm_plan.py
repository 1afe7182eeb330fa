# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Which host warms, hands to the controller, or is given each cache key (module_utils/instance/warm_cache.py)."""

from __future__ import annotations

DOCUMENTATION = r"""
name: isaac_sim_warm_plan
short_description: Decide, fleet-wide, which host warms each cache key and which hosts are given a copy
version_added: "0.3.0"
description:
  - Each key no host and not the controller keeps is warmed on the first host (in play order) whose instances
    need it, and fetched from there to the controller; a key a host keeps but the controller lacks is fetched
    from that host; every other host needing a key it lacks is given the controller's copy.
positional: _input, hostvars, kept
options:
  _input:
    description: The play's hosts, in order.
    type: list
    elements: str
    required: true
  hostvars:
    description: C(hostvars); each host's C(__isaac_sim_warm) is the probe of M(isaacsim.fleet.isaac_sim_warm_cache).
    type: dict
    required: true
  kept:
    description: The key ids whose archive the controller keeps.
    type: list
    elements: str
    required: true
"""

EXAMPLES = r"""
mine: "{{ ansible_play_hosts | isaacsim.fleet.isaac_sim_warm_plan(hostvars, kept) }}"
"""

RETURN = r"""
_value:
  description: Host name to C(warm), C(fetch) and C(copy), each a list of key ids.
  type: dict
"""


def isaac_sim_warm_plan(hosts: list, hostvars: dict, kept: list) -> dict:
    # on use, not at load: Ansible loads every filter file here to find one (docs/docsite/rst/contributing.rst, Layout)
    from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import warm_cache

    probes = []
    for name in hosts:
        probe = hostvars[name].get("__isaac_sim_warm") or {}
        probes.append((name, list((probe.get("cold") or {}).keys()), list(probe.get("held") or [])))
    return warm_cache.fleet_plan(probes, list(kept or []))


class FilterModule:
    def filters(self):
        return {"isaac_sim_warm_plan": isaac_sim_warm_plan}
