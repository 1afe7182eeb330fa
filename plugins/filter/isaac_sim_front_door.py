# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The front door's settings checked, and its files (module_utils/front/front_door.py)."""

from __future__ import annotations

from ansible.errors import AnsibleFilterError

DOCUMENTATION = r"""
name: isaac_sim_front_door
short_description: Check the front door's settings, or render its files (isaacsim.fleet.front_door)
version_added: "0.3.0"
description:
  - C(errors) lists what is wrong with the settings, each naming the variable and the fix.
  - C(services) renders, in order, each unit of the front door for M(isaacsim.fleet.isaac_sim_host_service)
    (C(name), C(state), C(files), C(remove)) - the login service, nginx, the TURN relay (stopped and
    removed when C(turn) is off).
  - C(removal) gives the same list for taking all of it away (every unit C(absent), with what goes with it);
    the settings are not read.
  - C(end_sessions) gives what the removal runs first (C(unit), C(store), C(argv)) - the fleet API's code ends
    every simulator session and place, each claim given back on its host, waiting up to C(wait) seconds.
positional: _input, what
options:
  _input:
    description:
      - The front door's settings - C(server_name), C(port), C(http_port), C(auth_port), C(api_port), C(login_rate),
        C(session_hours), C(sim) (the simulator sessions' rules), C(metrics_dir), C(users), C(backends),
        C(viewer_port_base), C(turn), C(turn_port), C(turn_min_port), C(turn_max_port), C(turn_gid); for C(services)
        also C(cert), C(key)
        (PEM text), C(auth_code) (the login service's code), C(store_code) (its store's code), C(api_code) (the
        fleet API's code), C(pool_code) (its sessions' pool) and C(turn_secret).
    type: dict
    required: true
  what:
    description: What to return.
    type: str
    choices: [errors, services, removal, end_sessions]
    required: true
"""

EXAMPLES = r"""
errors: "{{ settings | isaacsim.fleet.isaac_sim_front_door('errors') }}"
"""

RETURN = r"""
_value:
  description: A list of errors (C(errors)), or of the units with what each becomes (C(services), C(removal)), or
    the removal's first command (C(end_sessions)).
  type: raw
"""


def isaac_sim_front_door(settings: dict, what: str):
    # on use, not at load: Ansible loads every filter file here to find one (docs/docsite/rst/contributing.rst, Layout)
    from ansible_collections.isaacsim.fleet.plugins.module_utils.front import front_door
    from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout

    if what == "errors":
        return front_door.check(settings or {})
    if what == "services":
        errors = front_door.check(settings or {})
        if errors:
            raise AnsibleFilterError("; ".join(errors))
        return front_door.services(
            settings,
            layout.MANAGED,
            settings["cert"],
            settings["key"],
            {
                "auth": settings["auth_code"],
                "store": settings["store_code"],
                "api": settings["api_code"],
                "pool": settings["pool_code"],
            },
            settings.get("turn_secret", ""),
        )
    if what == "removal":
        # settings: only metrics_dir (the sessions' figures go with the door)
        gone = front_door.removal(str((settings or {}).get("metrics_dir") or ""))
        return [{"name": unit, "state": "absent", **spec} for unit, spec in gone.items()]
    if what == "end_sessions":
        return front_door.end_sessions(int((settings or {}).get("wait", 120)))
    raise AnsibleFilterError(f"isaac_sim_front_door: {what!r} is not errors, services, removal or end_sessions")


class FilterModule:
    def filters(self):
        return {"isaac_sim_front_door": isaac_sim_front_door}
