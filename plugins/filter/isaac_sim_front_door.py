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
  - C(files) renders, per unit, the files of the login service and of nginx for
    M(isaacsim.fleet.isaac_sim_host_service).
  - C(removal) gives, per unit, what M(isaacsim.fleet.isaac_sim_host_service) removes with it
    (C(files) and C(remove)); the settings are not read.
positional: _input, what
options:
  _input:
    description:
      - The front door's settings - C(server_name), C(port), C(http_port), C(auth_port), C(login_rate),
        C(session_hours), C(users), C(backends); for C(files) also C(cert), C(key) (PEM text) and
        C(auth_code) (the login service's code).
    type: dict
    required: true
  what:
    description: What to return.
    type: str
    choices: [errors, files, removal]
    required: true
"""

EXAMPLES = r"""
errors: "{{ settings | isaacsim.fleet.isaac_sim_front_door('errors') }}"
"""

RETURN = r"""
_value:
  description: A list of errors (C(errors)), or each unit's name to its files (C(files)) or to what goes with it
    (C(removal)).
  type: raw
"""


def isaac_sim_front_door(settings: dict, what: str):
    # on use, not at load: Ansible loads every filter file here to find one (README, Layout)
    from ansible_collections.isaacsim.fleet.plugins.module_utils.front import front_door
    from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout

    if what == "errors":
        return front_door.check(settings or {})
    if what == "files":
        errors = front_door.check(settings or {})
        if errors:
            raise AnsibleFilterError("; ".join(errors))
        return front_door.files(settings, layout.MANAGED, settings["cert"], settings["key"], settings["auth_code"])
    if what == "removal":
        return front_door.removal()
    raise AnsibleFilterError(f"isaac_sim_front_door: {what!r} is not errors, files or removal")


class FilterModule:
    def filters(self):
        return {"isaac_sim_front_door": isaac_sim_front_door}
