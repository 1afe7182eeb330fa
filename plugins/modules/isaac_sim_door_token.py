#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_door_token
short_description: Make, revoke and list the API tokens of the fleet's front door
version_added: "0.4.0"
description:
  - Runs on the front door host (M(isaacsim.fleet.isaac_sim_door_token) beside the login service of
    R(the front_door role,ansible_collections.isaacsim.fleet.front_door_role)), on the store the login service reads
    (an SQLite file of the state directory); the service sees a change at the next request, with no restart.
  - A token is C(isf_ID_SECRET). It acts as its user, with the user's role of the moment, and only within its scopes -
    C(read) (the fleet, status, logs an operator may read), C(use) (ask for a simulator session, end it), C(act)
    (start, stop, restart instances) and C(operate) (drain, remove, clean up). A viewer may hold C(read) and C(use)
    only. Programs send it as a bearer token in the
    C(Authorization) header.
  - Only the SHA-256 of its secret is kept; the token is returned once, when made. A user has one live token of a
    name; making it again (O(rotate=true)) replaces it, and the old one ends.
author: isaacsim.fleet contributors (@isaacsim-fleet)
extends_documentation_fragment:
  - isaacsim.fleet.attributes
  - isaacsim.fleet.attributes.platform
attributes:
  check_mode:
    support: full
    details: Says whether a token would be made or revoked; the store is not written and no token is returned.
  diff_mode:
    support: none
    details: No diff is returned.
  platform:
    platforms: debian
    details: The front door host as the front_door role sets it up.
options:
  user:
    description: The user the token acts as (one of C(front_door_users)). Not used with O(state=listed).
    type: str
  name:
    description: The token's name, unique per user (1-64 of C(A-Z a-z 0-9 . _ @ -)). Not used with O(state=listed).
    type: str
  scopes:
    description: What it may do.
    type: list
    elements: str
    choices: [read, use, act, operate]
    default: [read]
  days:
    description: How many days it is good for (1-365).
    type: int
    default: 30
  rotate:
    description: With O(state=present), make a new token even where a live one of that name is there (it ends).
    type: bool
    default: false
  state:
    description: C(present) makes the token unless a live one of that name is there; C(absent) revokes it; C(listed)
      changes nothing and returns every token.
    type: str
    choices: [present, absent, listed]
    default: present
  variable_prefix:
    description: What the user's variables are called before the option's name (C(front_door_token_)), named in
      errors.
    type: str
    default: ""
  store:
    description: The login service's store.
    type: path
    default: /var/lib/isaac-sim-front-door/door.db
  users_file:
    description: The front door's users (their roles), as the role writes them.
    type: path
    default: /etc/isaac-sim/front-door/users.json
notes:
  - The secret is in the result's C(token) only; give the task C(no_log) and keep it where only its program reads it.
"""

EXAMPLES = r"""
- name: A token for the CI job that restarts instances
  isaacsim.fleet.isaac_sim_door_token:
    user: olga
    name: ci-restarts
    scopes: [read, act]
    days: 90
  register: made
  no_log: true
"""

RETURN = r"""
token:
  description: The token, C(isf_ID_SECRET); only when one was made (not in check mode).
  returned: when a token was made
  type: str
record:
  description: The token made, kept or revoked - C(id), C(user), C(name), C(scopes), C(created), C(expires) (epoch
    seconds), C(state) (C(active), C(expired), C(revoked)).
  returned: with O(state=present) or O(state=absent), when there is one
  type: dict
tokens:
  description: Every token of the store, newest first, as in RV(record).
  returned: success
  type: list
  elements: dict
"""

import json
import os

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.front import door_store


def main():
    module = AnsibleModule(
        argument_spec=dict(
            user=dict(type="str"),
            name=dict(type="str"),
            scopes=dict(type="list", elements="str", choices=list(door_store.SCOPES), default=["read"]),
            days=dict(type="int", default=30),
            rotate=dict(type="bool", default=False),
            state=dict(type="str", choices=["present", "absent", "listed"], default="present"),
            variable_prefix=dict(type="str", default=""),
            store=dict(type="path", default="/var/lib/isaac-sim-front-door/door.db"),
            users_file=dict(type="path", default="/etc/isaac-sim/front-door/users.json"),
        ),
        required_if=[("state", "present", ("user", "name")), ("state", "absent", ("user", "name"))],
        supports_check_mode=True,
    )
    p = module.params
    try:
        with open(p["users_file"], encoding="utf-8") as f:
            users = json.load(f)
        if module.check_mode and not os.path.exists(p["store"]):
            # nothing is written in check mode, not even an empty store
            module.exit_json(changed=p["state"] == "present", tokens=[])
        store = door_store.Store(p["store"])
    except (OSError, ValueError) as exc:
        module.fail_json(
            msg=f"The front door's users or store cannot be read ({exc}). Fix: run playbooks/front_door.yml first."
        )
    result = token(module, store, users, p) if p["state"] != "listed" else {"changed": False}
    module.exit_json(tokens=store.tokens(), **result)


def token(module, store, users, p) -> dict:
    found = store.find_token(p["user"], p["name"])
    if p["state"] == "absent":
        live = found is not None and found["state"] != "revoked"
        if live and not module.check_mode:
            store.revoke(p["user"], p["name"])
            found = dict(found, state="revoked")
        return {"changed": live, **({"record": found} if found else {})}
    record = users.get(p["user"])
    record = record if isinstance(record, dict) else {}
    errors = door_store.token_errors(p["user"], record.get("role"), p["name"], p["scopes"], p["days"])
    if errors:
        module.fail_json(msg=" ".join(p["variable_prefix"] + e for e in errors))
    if found is not None and found["state"] == "active" and not p["rotate"]:
        return {"changed": False, "record": found}
    if module.check_mode:
        return {"changed": True}
    text, made = store.make_token(p["user"], p["name"], p["scopes"], p["days"], record.get("hash", ""))
    return {"changed": True, "token": text, "record": made}


if __name__ == "__main__":
    main()
