# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Whether a host service is as wanted already, from what the plan read of it: the deploy then leaves out
its module call (one round trip less on a re-run). The decision is host_service.in_place, the module's own."""

from __future__ import annotations

DOCUMENTATION = r"""
name: isaac_sim_host_service_in_place
short_description: Whether M(isaacsim.fleet.isaac_sim_host_service) would change nothing
version_added: "0.3.0"
description:
  - True when M(isaacsim.fleet.isaac_sim_host_service) with these files and directories (state started) would
    change nothing on the host, as M(isaacsim.fleet.isaac_sim_plan) read it (C(host.host_services[UNIT])) - every
    file with the same content (compared by digest), mode and owner, every directory with its owner and mode,
    the unit enabled and running.
  - False when the plan did not read one of the paths, or did not read the service at all - the module then runs.
positional: _input, seen, directories
options:
  _input:
    description: The module's C(files), each path to its C(content), C(mode) and where wanted C(uid) and C(gid).
    type: dict
    required: true
  seen:
    description: The service as the plan read it (C(__isaac_sim_host.host_services[UNIT])); empty when it was not read.
    type: dict
    required: true
  directories:
    description: The module's C(directories), each with its C(path), C(uid), C(gid) and C(mode).
    type: list
    elements: dict
    default: []
"""

EXAMPLES = r"""
in_place: "{{ files | isaacsim.fleet.isaac_sim_host_service_in_place(plan_result.host.host_services[unit]) }}"
"""

RETURN = r"""
_value:
  description: Whether the module would change nothing.
  type: bool
"""


def isaac_sim_host_service_in_place(files, seen, directories=None) -> bool:
    # on use, not at load: Ansible loads every filter file here to find one (docs/docsite/rst/contributing.rst, Layout)
    from ansible_collections.isaacsim.fleet.plugins.module_utils.host import host_service

    params = {"files": dict(files or {}), "directories": list(directories or []), "state": "started"}
    return host_service.in_place(params, dict(seen or {}))


class FilterModule:
    def filters(self):
        return {"isaac_sim_host_service_in_place": isaac_sim_host_service_in_place}
