# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""A password's hash for the front door's users (module_utils/front/door_auth.py)."""

from __future__ import annotations

from ansible.errors import AnsibleFilterError

DOCUMENTATION = r"""
name: isaac_sim_password_hash
short_description: Hash a password for the front door's users (isaacsim.fleet.front_door)
version_added: "0.3.0"
description:
  - PBKDF2-SHA256 in passlib's format (C($pbkdf2-sha256$ROUNDS$SALT$SUM)), the same as Ansible's
    C(password_hash('pbkdf2_sha256')) writes where passlib is installed; made with Python's standard
    library alone, with a new random salt on every call.
  - Put the result in C(front_door_users) (in a vault); the password itself never reaches a host.
positional: _input, rounds
options:
  _input:
    description: The password.
    type: str
    required: true
  rounds:
    description: PBKDF2 iterations (at least 10000).
    type: int
    default: 29000
"""

EXAMPLES = r"""
# ansible localhost -m debug -a "msg={{ 'PASSWORD' | isaacsim.fleet.isaac_sim_password_hash }}"
hash: "{{ password | isaacsim.fleet.isaac_sim_password_hash }}"
"""

RETURN = r"""
_value:
  description: The hash.
  type: str
"""


def isaac_sim_password_hash(password, rounds=29000):
    from ansible_collections.isaacsim.fleet.plugins.module_utils.front import door_auth

    if not isinstance(password, str) or not password:
        raise AnsibleFilterError("isaac_sim_password_hash: give the password as a non-empty string")
    if int(rounds) < door_auth.MIN_ROUNDS:
        raise AnsibleFilterError(f"isaac_sim_password_hash: rounds {rounds} is below {door_auth.MIN_ROUNDS}")
    return door_auth.hash_password(password, int(rounds))


class FilterModule:
    def filters(self):
        return {"isaac_sim_password_hash": isaac_sim_password_hash}
