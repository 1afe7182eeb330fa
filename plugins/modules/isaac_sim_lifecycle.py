#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_lifecycle
short_description: The one lifecycle of a host's Isaac Sim instances - apply, start, stop, restart, remove
version_added: "0.3.0"
description:
  - Every change to the instances of a host goes through this module - deploys, day-2 actions, scale-down,
    cleanup, rolling restarts and upgrades - so the steps are the same everywhere.
  - O(action=apply) brings the host to a plan of M(isaacsim.fleet.isaac_sim_plan) - directories, the template
    unit, the target, the host-side scripts and each instance's env file. Instances that are not serving
    (new, stopped, failed) are started together. A serving instance whose env file or the shared files
    changed is restarted one at a time - stopped first if stuck activating, its start counter reset, restarted
    (C(systemctl restart) returns once the readiness gate saw the ready line), then soaked for
    O(soak_seconds). On the first failure that instance goes back to its previous env file (pinned to its
    previous image id when the tag has moved) and the shared files to theirs, the instances after it are left
    untouched, and the module fails naming the instance and the reason. Instances the plan no longer has are
    stopped, disabled and their env files removed (scale-down), before anything starts.
  - With O(defer_running), a host where a serving instance would restart is left unchanged and reported as
    RV(deferred), so the playbook can roll it in canary batches.
  - With addresses of their own (the plan's C(network)), the Docker macvlan network is created before the first
    instance changes, and removed once no instance wants it and nobody is on it; a network in use is never
    changed under its containers.
  - On the host's network, the instances' and companions' ports (the plan's C(reserved_ports)) are kept out of the
    host's ephemeral range in C(net.ipv4.ip_local_reserved_ports), in the kernel and in
    C(/etc/sysctl.d/99-zz-isaac-sim-reserved-ports.conf), before an instance binds a new one, so that no outgoing
    connection from the host takes a port an instance is about to bind. Ports the host reserved itself are kept;
    those the collection added leave with the last instance that has them.
  - O(action=restart) restarts O(ids) one at a time, each ready and soaked. O(action=start) starts them together,
    O(action=stop) stops them (they stay enabled), O(action=remove) stops, disables and forgets them; caches, logs
    and data stay unless O(purge).
author: isaacsim.fleet contributors (@isaacsim-fleet)
extends_documentation_fragment:
  - isaacsim.fleet.attributes
  - isaacsim.fleet.attributes.platform
  - isaacsim.fleet.attributes.action
  - isaacsim.fleet.layout.data_root
attributes:
  action:
    support: full
    details: Runs the module on the host as a background job and renews this run's hold on the host's lock while it
      waits; an apply looks in check mode first and starts no job when nothing would change.
  check_mode:
    support: full
    details: Reports what would be written, started, restarted and removed; changes nothing.
  diff_mode:
    support: partial
    details: With O(action=apply), shows the shared files (units, scripts); env files may hold secrets and are not
      shown.
  platform:
    platforms: posix
options:
  action:
    description: What to do.
    type: str
    choices: [apply, start, stop, restart, remove]
    default: apply
  ids:
    description: Instance numbers for O(action=start), V(stop), V(restart) and V(remove).
    type: list
    elements: int
    default: []
  plan:
    description: The plan of M(isaacsim.fleet.isaac_sim_plan) (its RV(isaacsim.fleet.isaac_sim_plan#module:plan)),
      for O(action=apply).
    type: dict
  image_id:
    description: Id of the planned image on this host, written to each env file so a new image restarts its
      instances.
    type: str
    default: unknown
  secret_env:
    description: Secret container variables; the env files holding them are mode 0600.
    type: dict
    default: {}
  scripts:
    description: Content of the host-side scripts (C(isaac-sim-run), C(isaac-sim-ready), C(isaac-sim-ports),
      C(isaac-sim-cache-state), C(isaac-sim-policy)) and of the container policy's code that C(isaac-sim-policy)
      reads beside them (C(docker_cli.py), C(container_policy.py) from the host library), installed in the
      layout's libexec directory.
    type: dict
    default: {}
  managed:
    description: The stamp written at the top of every file.
    type: str
    default: Ansible managed (isaacsim.fleet)
  soak_seconds:
    description: How long a restarted instance must stay ready with its restart count unchanged.
    type: float
    default: 0
  held_wait:
    description:
      - With O(action=apply) or O(action=restart), how many seconds to wait for a test run or a session that holds
        an instance the call would restart to give it back. Once the wait is over, the instance is left as it is
        (its settings too, so the next deploy rolls it) and listed in RV(left); the other instances roll.
      - A port layout change cannot leave an instance behind; it stops before a held instance, as a failure.
    type: float
    default: 0
    version_added: "0.4.0"
  end_sessions:
    description:
      - With O(action=apply) or O(action=restart), end the sessions of people (the front door's simulator sessions)
        that hold an instance the call would restart, after this many seconds of warning, instead of waiting for
        them as for a test run. The session's marker says when, so the front door warns its holder in the page;
        at that time the claim ends on the host and the instance rolls with the others.
      - Test runs are never ended so. Omitted, sessions are waited for and left as test runs are (O(held_wait)).
    type: float
    version_added: "0.4.0"
  defer_running:
    description: With O(action=apply), change nothing on a host where a serving instance would restart.
    type: bool
    default: false
  remove_others:
    description: With O(action=apply), remove the instances this collection set up earlier that the plan no
      longer has.
    type: bool
    default: true
  purge:
    description: Also delete the caches, logs and data of removed instances - under O(data_root), or with
      O(action=apply) under the plan's C(data_root).
    type: bool
    default: false
  controller_run:
    description:
      - The playbook run that asks, filled by the action plugin of the same name. When that run holds the
        host's lock (M(isaacsim.fleet.isaac_sim_lock)), the action plugin renews it while it waits, and a
        lock not renewed for 30 s means the controller is gone (Ctrl-C, killed); the rollout stops before
        the next instance, the one in hand left ready or reverted, and says so in the journal
        (C(journalctl -t isaac-sim-lifecycle)); the next run's lock note repeats it.
      - Left empty for a task with its own C(async), which Ansible polls without renewing the lock.
    type: str
    default: ""
notes:
  - The module runs for as long as the instances take; one call per host keeps Ansible's per-task cost out of
    a rollout's time.
seealso:
  - module: isaacsim.fleet.isaac_sim_plan
  - module: isaacsim.fleet.isaac_sim_info
"""

EXAMPLES = r"""
- name: Apply the plan, starting new instances and rolling changed ones one at a time
  isaacsim.fleet.isaac_sim_lifecycle:
    plan: "{{ planned.plan }}"
    image_id: "{{ image.images[0].Id }}"
    scripts:
      isaac-sim-run: "{{ lookup('ansible.builtin.file', 'isaac-sim-run') }}"
      isaac-sim-ready: "{{ lookup('ansible.builtin.file', 'isaac-sim-ready') }}"
      isaac-sim-ports: "{{ lookup('ansible.builtin.file', 'isaac-sim-ports') }}"
    soak_seconds: 30

- name: Restart instances 0 and 1, one at a time, each soaked 30 s
  isaacsim.fleet.isaac_sim_lifecycle:
    action: restart
    ids: [0, 1]
    soak_seconds: 30
"""

RETURN = r"""
plan:
  description:
    - What O(action=apply) found to do - shared files to write, instances to start, roll, remove, enable.
    - C(held) names the holder of each instance to roll that a test run or a session holds (see O(held_wait)).
  returned: action is apply
  type: dict
  sample: {"files": [], "start": [], "roll": [0, 1], "remove": [], "enable": [], "reserved_ports": false}
deferred:
  description: O(defer_running) left the host unchanged because serving instances would restart.
  returned: action is apply
  type: bool
done:
  description: Instances changed, in order, each with C(action) (start, apply, restart) and its timings.
  returned: always
  type: list
  elements: dict
  sample: [{"id": 0, "action": "apply", "restart_s": 6.2, "soak_s": 30.0}]
failed_instance:
  description:
    - The instance that failed, why, and whether it went back to its previous settings; the first of
      RV(failed_instances) when more than one failed.
  returned: always
  type: dict
  sample: {"id": 0, "reason": "isaac-sim-0 was not ready within 20 s", "reverted": true,
           "reverted_to": "nvcr.io/nvidia/isaac-sim:5.0.0", "revert_error": null, "left": "running"}
failed_instances:
  description:
    - Every instance that failed, each as RV(failed_instance) says it. More than one only where instances
      started together (new, stopped or failed ones) and several failed; each of those was stopped and a
      new one forgotten, one that had settings before went back to them. Empty when none failed.
  returned: always
  type: list
  elements: dict
  sample: [{"id": 2, "reason": "isaac-sim-2 was not ready within 20 s", "reverted": null, "left": "stopped"},
           {"id": 3, "reason": "isaac-sim-3 was not ready within 20 s", "reverted": null, "left": "stopped"}]
untouched:
  description: Instances not reached because of the failure.
  returned: always
  type: list
  elements: int
left:
  description:
    - Instances left as they were for the test run or session that holds them (O(held_wait)), each with its
      C(holder). The call does not fail for them.
  returned: always
  type: list
  elements: dict
  sample: [{"id": 2, "holder": "session-3f2a"}]
  version_added: "0.4.0"
ended:
  description:
    - Instances whose people's sessions the call ended after their warning (O(end_sessions)), each with the
      session's C(holder); each then rolled with the others.
  returned: always
  type: list
  elements: dict
  sample: [{"id": 1, "holder": "session-3f2a"}]
  version_added: "0.4.0"
directories:
  description: Directories created or given the container user's owner and mode.
  returned: action is apply
  type: list
  elements: str
network:
  description:
    - What was done to the instances' macvlan network C(isaac-sim-macvlan) - C(create), C(recreate) (nobody was on
      it), C(remove) (no instance wants it and nobody is on it), C(kept) (no longer wanted, but a container is still
      on it), or null. In check mode, what would be done.
  returned: action is apply or remove
  type: str
reserved_ports:
  description: Whether the host's reserved ports (C(net.ipv4.ip_local_reserved_ports)) changed, or would in check mode.
  returned: action is remove and no instance is left
  type: bool
"""

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import lifecycle, lifecycle_call

ARGUMENT_SPEC = dict(
    action=dict(type="str", default="apply", choices=["apply", *lifecycle_call.DAY2]),
    ids=dict(type="list", elements="int", default=[]),
    plan=dict(type="dict"),
    image_id=dict(type="str", default="unknown"),
    secret_env=dict(type="dict", default={}, no_log=True),
    scripts=dict(type="dict", default={}),
    managed=dict(type="str", default=layout.MANAGED),
    soak_seconds=dict(type="float", default=0),
    held_wait=dict(type="float", default=0),
    end_sessions=dict(type="float"),
    defer_running=dict(type="bool", default=False),
    remove_others=dict(type="bool", default=True),
    purge=dict(type="bool", default=False),
    data_root=dict(type="path", default=layout.DATA_ROOT),
    controller_run=dict(type="str", default=""),
)


def main():
    module = AnsibleModule(
        argument_spec=ARGUMENT_SPEC,
        required_if=[("action", "apply", ["plan"])],
        supports_check_mode=True,
    )
    try:
        out = lifecycle_call.call(lifecycle.bind(module), module.params, check=module.check_mode, diff=module._diff)
    except lifecycle_call.LifecycleError as exc:
        module.fail_json(msg=exc.msg, **exc.fields)
    module.exit_json(**out)


if __name__ == "__main__":
    main()
