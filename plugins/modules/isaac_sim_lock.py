#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_lock
short_description: Hold a host for one playbook run at a time
version_added: "0.3.0"
description:
  - Every playbook of the collection that changes instances takes the host's lock before it plans
    and gives it back at its end, so two deploys never mix their settings on one host.
  - The lock is C(/run/lock/isaac-sim.json); a reboot frees it. Taking it is one critical section
    under C(flock), so two runs never both hold it.
  - A lock held by another run is taken over only when that run has ended (its C(ansible-playbook)
    process on this controller is gone), when it was not renewed for I(stale_after) seconds, or
    with I(break_lock).
  - The action plugin of the same name fills I(holder) from the controller, waits up to
    I(wait) seconds for a held lock and finds holders that have ended.
  - Taking and renewing the lock is not a change of the host's configuration; it reports
    C(changed=false). In check mode nothing is written; a lock held by another run is reported.
author: isaacsim.fleet contributors (@isaacsim-fleet)
extends_documentation_fragment:
  - isaacsim.fleet.attributes
  - isaacsim.fleet.attributes.platform
  - isaacsim.fleet.attributes.action
attributes:
  action:
    support: full
    details: Fills O(holder) from the controller, waits up to O(wait) seconds for a held lock and finds holders that
      have ended.
  check_mode:
    support: full
    details: Says whether the lock would be taken or renewed and who holds it; writes nothing.
  diff_mode:
    support: none
    details: No diff is returned.
  platform:
    platforms: posix
options:
  state:
    description:
      - C(present) takes or renews the lock, C(absent) gives it back, C(renewed) only renews it when this run
        holds it (the heartbeat of M(isaacsim.fleet.isaac_sim_lifecycle)'s action plugin).
    type: str
    choices: [present, absent, renewed]
    default: present
  holder:
    description:
      - This run, filled by the action plugin (id, user, controller, pid, started, play).
    type: dict
    required: true
  stale_after:
    description: Seconds after which a lock its run has not renewed is taken over; 0 never.
    type: int
    default: 3600
  break_lock:
    description: Take the lock from whichever run holds it (the operator knows that run is dead).
    type: bool
    default: false
  dead:
    description: The id of a holder the controller found ended; filled by the action plugin.
    type: str
    default: ""
  wait:
    description: Seconds the action plugin waits for another run's lock before it fails.
    type: int
    default: 0
"""

EXAMPLES = r"""
- name: Hold this host for this run
  isaacsim.fleet.isaac_sim_lock:
    wait: 600
"""

RETURN = r"""
acquired:
  description: Whether this run holds the lock now.
  returned: always
  type: bool
holder:
  description: The run that holds the lock after the call (null when free).
  returned: always
  type: dict
note:
  description: What happened to a lock another run held (taken over from whom and why).
  returned: always
  type: str
"""

import time

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import runlock

ARGUMENT_SPEC = dict(
    state=dict(type="str", choices=["present", "absent", "renewed"], default="present"),
    **runlock.request_options(holder_required=True),
)


def main():
    module = AnsibleModule(argument_spec=ARGUMENT_SPEC, supports_check_mode=True)
    try:
        out = runlock.request(module.params, time.time(), module.check_mode)
    except runlock.LockError as exc:
        module.fail_json(msg=str(exc))
    module.exit_json(changed=False, **out)


if __name__ == "__main__":
    main()
