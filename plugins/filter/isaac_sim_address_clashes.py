# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Addresses given to instances on more than one host."""

from __future__ import annotations

DOCUMENTATION = r"""
name: isaac_sim_address_clashes
short_description: Errors for an instance address planned on two hosts
version_added: "0.3.0"
description:
  - For the plans of several hosts (M(isaacsim.fleet.isaac_sim_plan)), one error per address that
    instances on two hosts would both take (O(isaacsim.fleet.isaac_sim#role:main:isaac_sim_network_mode=macvlan)).
    Each host's own plan already refuses a clash inside the host.
positional: _input, hosts
options:
  _input:
    description: The plans, in the order of O(hosts); a host without a plan gives an empty mapping.
    type: list
    elements: dict
    required: true
  hosts:
    description: The hosts the plans belong to.
    type: list
    elements: str
    required: true
"""

EXAMPLES = r"""
msg: >-
  {{ ansible_play_hosts | map('extract', hostvars) | map(attribute='plan', default={})
     | isaacsim.fleet.isaac_sim_address_clashes(ansible_play_hosts) }}
"""

RETURN = r"""
_value:
  description: One message per clashing address, naming the instances and hosts; empty when none clash.
  type: list
  elements: str
"""


def address_clashes(plans, hosts) -> list:
    # on use, not at load: Ansible loads every filter file here to find one (docs/docsite/rst/contributing.rst, Layout)
    from ansible_collections.isaacsim.fleet.plugins.module_utils.instance.network import clashes

    by_host = {}
    for host, plan in zip(hosts, plans):
        if isinstance(plan, dict):
            by_host[host] = {i["id"]: i["address"] for i in plan.get("instances", []) if i.get("address")}
    return clashes(by_host)


class FilterModule:
    def filters(self):
        return {"isaac_sim_address_clashes": address_clashes}
