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
attributes:
  check_mode:
    support: full
    description: Reports what would be written, started, restarted and removed; changes nothing.
  diff_mode:
    support: partial
    description: Shows the shared files (units, scripts); env files may hold secrets and are not shown.
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
    description: Content of the host-side scripts (C(isaac-sim-run), C(isaac-sim-ready), C(isaac-sim-ports)),
      installed in the layout's libexec directory.
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
    description: Also delete the caches, logs and data of removed instances.
    type: bool
    default: false
  data_root:
    description: Where the instances' caches, logs and data are (C(DATA_ROOT/instance-N)), for O(purge).
      O(action=apply) takes it from the plan.
    type: path
    default: /var/lib/isaac-sim
  controller_run:
    description:
      - The playbook run that asks, filled by the action plugin of the same name. When that run holds the
        host's lock (M(isaacsim.fleet.isaac_sim_lock)), the action plugin renews it while it waits, and a
        lock not renewed for 30 s means the controller is gone (Ctrl-C, killed); the rollout stops before
        the next instance, the one in hand left ready or reverted, and says so in the journal
        (C(journalctl -t isaac-sim-lifecycle)); the next run's lock note repeats it.
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
  description: What O(action=apply) found to do - shared files to write, instances to start, roll, remove, enable.
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
  description: The instance that failed, why, and whether it went back to its previous settings.
  returned: always
  type: dict
  sample: {"id": 0, "reason": "isaac-sim-0 was not ready within 20 s", "reverted": true,
           "reverted_to": "nvcr.io/nvidia/isaac-sim:5.0.0", "revert_error": null, "left": "running"}
untouched:
  description: Instances not reached because of the failure.
  returned: always
  type: list
  elements: int
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

import os
import time

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import dirs
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerError, DockerSocket
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import hostprobe, lifecycle, network, runlock

# the target's links: every instance enabled on this host
_WANTS = os.path.join(layout.UNIT_DIR, layout.TARGET + ".wants")


def _want(module, host, found):
    """The wanted state of the host, from the plan; found: the companions on the host now."""
    p = module.params
    plan = p["plan"]
    env_mode = 0o600 if p["secret_env"] else 0o644
    files = {
        os.path.join(layout.UNIT_DIR, layout.UNIT_TEMPLATE): (
            layout.render_unit(plan["settings"], p["managed"]),
            0o644,
        ),
        os.path.join(layout.UNIT_DIR, layout.TARGET): (layout.render_target(p["managed"]), 0o644),
    }
    for name in layout.SCRIPTS:
        if name not in p["scripts"]:
            module.fail_json(msg=f"scripts: {name} is missing. Fix: pass the role's files/{name}.")
        text = p["scripts"][name]
        files[os.path.join(layout.LIBEXEC_DIR, name)] = (text if text.endswith("\n") else text + "\n", 0o755)
    for unit in plan.get("companion_units", []):
        files[os.path.join(layout.UNIT_DIR, layout.companion_template(unit["name"]))] = (
            layout.render_companion_unit(unit, plan["settings"], p["managed"]),
            0o644,
        )
    # templates of companions the plan no longer has: removed once their units are gone
    for name in hostprobe.companion_templates(layout.UNIT_DIR):
        files.setdefault(os.path.join(layout.UNIT_DIR, layout.companion_template(name)), (None, None))
    instances = {
        inst["id"]: layout.render_env(inst, plan, p["image_id"], p["secret_env"], p["managed"])
        for inst in plan["instances"]
    }
    companions = {
        inst["id"]: {c["name"]: layout.render_companion_env(c, plan, p["managed"]) for c in inst.get("companions", [])}
        for inst in plan["instances"]
    }
    gone = []
    if p["remove_others"]:
        gone = [i for i in hostprobe.existing_instances(layout.CONFIG_DIR, _WANTS) if i not in instances]
    return {
        "files": files,
        "instances": instances,
        "companions": companions,
        "companions_found": found,
        "env_mode": env_mode,
        "remove": gone,
        "purge": p["purge"],
        "data_root": plan["layout"]["data_root"],
        "soak": p["soak_seconds"],
        "defer_running": p["defer_running"],
        "reserve": plan.get("reserved_ports", []),
        "managed": p["managed"],
    }


def _network(module, needed):
    """Our macvlan network as Docker has it now, or None. Without Docker (a fresh host, in check
    mode) there is none; that is an error only when the instances need it."""
    try:
        return network.parse_network(DockerSocket().network(layout.NETWORK))
    except DockerError as exc:
        if needed:
            module.fail_json(msg=f"could not ask Docker for the network {layout.NETWORK}: {exc}")
        return None


def _addressed_instances():
    """Instances whose env file gives them an address of their own: stopped or crash-looping ones
    have no container on the network, and still need it."""
    found = []
    for name in sorted(os.listdir(layout.CONFIG_DIR)) if os.path.isdir(layout.CONFIG_DIR) else []:
        i = layout.instance_id(layout.ENV_FILE_RE, name)
        if i is None:
            continue
        try:
            with open(os.path.join(layout.CONFIG_DIR, name)) as fh:
                if layout.parse(fh.read()).get(layout.K_ADDRESS):
                    found.append(i)
        except OSError:
            continue
    return found


def _drop_network(module, host):
    """Remove our network when nobody is on it and no instance is set to use it: 'remove',
    'kept' (a container is on it, or an instance is set to use it), or None."""
    found = _network(module, needed=False)
    if not found or not found.get("ours"):
        return None
    if found["containers"] or _addressed_instances():
        return "kept"
    if module.check_mode:
        return "remove"
    rc, _out, err = host.run(network.remove_argv())
    if rc != 0:
        module.fail_json(msg=f"could not remove the network {layout.NETWORK}: {err.strip()}")
    return "remove"


def _directories(plan):
    """(paths, uid, gid) of the instances' own directories, owned by the release's container user."""
    paths = [inst["root"] for inst in plan["instances"]] + [d for inst in plan["instances"] for d in inst["dirs"]]
    return paths, plan["uid"], plan["gid"]


def _diff(host, files):
    out = []
    for path, (text, _mode) in sorted(files.items()):
        before = host.read(path)
        if before != text:
            out.append({"before_header": path, "after_header": path, "before": before or "", "after": text})
    return out


def main():
    module = AnsibleModule(
        argument_spec=dict(
            action=dict(type="str", default="apply", choices=["apply", "start", "stop", "restart", "remove"]),
            ids=dict(type="list", elements="int", default=[]),
            plan=dict(type="dict"),
            image_id=dict(type="str", default="unknown"),
            secret_env=dict(type="dict", default={}, no_log=True),
            scripts=dict(type="dict", default={}),
            managed=dict(type="str", default="Ansible managed (isaacsim.fleet)"),
            soak_seconds=dict(type="float", default=0),
            defer_running=dict(type="bool", default=False),
            remove_others=dict(type="bool", default=True),
            purge=dict(type="bool", default=False),
            data_root=dict(type="path", default=layout.DATA_ROOT),
            controller_run=dict(type="str", default=""),
        ),
        required_if=[("action", "apply", ["plan"])],
        supports_check_mode=True,
    )
    p = module.params
    host = lifecycle.bind(module)
    run = p["controller_run"]
    held = run and (runlock.read() or {}).get("id") == run
    if held and not module.check_mode:
        host.interrupted = lambda: runlock.gone(run, time.time())
    out = dict(changed=False, done=[], failed_instance=None, untouched=[])
    found = hostprobe.existing_companions(layout.CONFIG_DIR)

    if p["action"] == "apply":
        want = _want(module, host, found)
        paths, uid, gid = _directories(p["plan"])
        dir_changes = dirs.wanted_changes(paths, uid, gid, 0o750)
        wanted_net = p["plan"].get("network") or {"mode": network.HOST}
        net_todo = network.action(wanted_net, _network(module, needed=wanted_net["mode"] == network.MACVLAN))
        if net_todo == "conflict":  # the plan refuses it; only a change made since gets here
            module.fail_json(
                msg=f"the network {layout.NETWORK} differs from the plan's and is in use; nothing was changed. "
                "Fix: plan again (isaac_sim_plan says how to move the instances off it)."
            )
        creates = net_todo in ("create", "recreate")
        applied = []

        def prepare():
            if creates:
                if net_todo == "recreate":
                    host.run(network.remove_argv())
                rc, _out, err = host.run(network.create_argv(wanted_net))
                if rc != 0:
                    module.fail_json(
                        msg=f"could not create the network {layout.NETWORK} ({wanted_net['parent']}, "
                        f"{wanted_net['subnet']}): {err.strip()}; nothing else was changed"
                    )
            dirs.apply(dir_changes, uid, gid, 0o750)
            applied.append(True)

        def reown(i):
            """Hand instance i's caches, logs and data to the new container user: kept, not wiped."""
            for root, subdirs, names in os.walk(layout.data_dir(i, want["data_root"])):
                os.lchown(root, uid, gid)
                for name in names + [d for d in subdirs if os.path.islink(os.path.join(root, d))]:
                    os.lchown(os.path.join(root, name), uid, gid)

        want["reown"] = reown

        want["prepare"] = prepare
        diff = _diff(host, want["files"]) if module._diff else None
        try:
            result = lifecycle.apply(host, want, check=module.check_mode)
            if (dir_changes or creates) and not applied and not module.check_mode and not result["deferred"]:
                prepare()
        except OSError as exc:
            module.fail_json(msg=f"could not write the host's files: {exc}", **out)
        net_done = net_todo if creates else None
        # once every instance is off it (the plan moved them to the host's network)
        if net_todo == "remove" and not result["deferred"] and not result["failed"]:
            net_done = "remove" if module.check_mode else _drop_network(module, host)
        host_changed = bool(dir_changes or creates or net_done == "remove") and not result["deferred"]
        out.update(
            plan=result["plan"],
            deferred=result["deferred"],
            directories=sorted({path for path, _what in dir_changes}),
            network=None if result["deferred"] else net_done,
            changed=result["changed"] or host_changed,
        )
        if diff:
            out["diff"] = diff
    elif p["action"] == "restart":
        result = lifecycle.restart_each(host, p["ids"], p["soak_seconds"], check=module.check_mode, companions=found)
    elif module.check_mode:
        result = {"done": [{"id": i, "action": p["action"]} for i in p["ids"]], "failed": None, "untouched": []}
        out["changed"] = bool(p["ids"])
    elif p["action"] == "start":
        result = {"done": [], "failed": None, "untouched": []}
        for i, (ok, reason) in lifecycle.start(host, p["ids"], companions=found).items():
            if ok:
                result["done"].append({"id": i, "action": "start"})
            elif result["failed"] is None:
                result["failed"] = {"id": i, "reason": reason, "reverted": None, "left": "failed"}
        out["changed"] = bool(p["ids"])
    else:
        if p["action"] == "stop":
            lifecycle.stop(host, p["ids"])
        else:
            lifecycle.remove(host, p["ids"], p["purge"], p["data_root"], companions=found)
            # the last instance on it gone (cleanup, scale to 0): the network goes too, and the ports
            out["network"] = _drop_network(module, host)
            if not hostprobe.existing_instances(layout.CONFIG_DIR, _WANTS):
                try:
                    out["reserved_ports"] = lifecycle.reserve(host, [], p["managed"], grow=False)
                except OSError as exc:
                    module.fail_json(msg=str(exc))
        result = {"done": [{"id": i, "action": p["action"]} for i in p["ids"]], "failed": None, "untouched": []}
        out["changed"] = bool(p["ids"]) or out.get("network") == "remove" or bool(out.get("reserved_ports"))

    out.update(done=result["done"], failed_instance=result["failed"], untouched=result["untouched"])
    if p["action"] == "restart":
        out["changed"] = result["changed"]
    if result.get("interrupted"):
        runlock.record(
            {
                "run": run,
                "at": time.time(),
                "interrupted": result["interrupted"],
                "done": [d["id"] for d in result["done"]],
                "untouched": result["untouched"],
            }
        )
        out["changed"] = out["changed"] or result["changed"]
        module.fail_json(
            msg=f"rollout interrupted: {result['interrupted']}; it stopped before "
            f"{', '.join(layout.container(i) for i in result['untouched'])}, which are as they were",
            interrupted=result["interrupted"],
            **out,
        )
    failed = result["failed"]
    if failed:
        if failed.get("reverted") is None:
            back = (
                "it was stopped (there are no earlier settings to go back to)"
                if failed.get("left") == "stopped"
                else ""
            )
        elif failed.get("reverted"):
            back = f"it went back to {failed.get('reverted_to')}" + (
                " and is ready again" if failed.get("left") == "running" else ""
            )
        else:
            back = f"going back failed too: {failed.get('revert_error')}"
        untouched = (
            f"; not reached: {', '.join(layout.container(i) for i in result['untouched'])}"
            if result["untouched"]
            else ""
        )
        module.fail_json(
            msg=f"{layout.container(failed['id'])}: {failed['reason']}" + (f"; {back}" if back else "") + untouched,
            **out,
        )
    module.exit_json(**out)


if __name__ == "__main__":
    main()
