# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""One call of the isaac_sim_lifecycle module: what the host has now, the one lifecycle
(lifecycle.py) asked to apply a plan or to start, stop, restart or remove instances, and the
result with its message.

Every read and change of the host goes through the lifecycle's Host (its run, read, write,
find, network, ...), which the module binds to the real host and the unit tests to a scripted
one; the instances' own directories are made and handed over on the real file system (under the
plan's data root). The lock's files are runlock's.
"""

from __future__ import annotations

import os

from ansible_collections.isaacsim.fleet.plugins.module_utils.host import dirs
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerError
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import (
    firewall,
    hostprobe,
    lifecycle,
    network,
    runlock,
    unit_files,
)
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance.lifecycle import Host

# the target's links: every instance enabled on this host
_WANTS = os.path.join(layout.UNIT_DIR, layout.TARGET + ".wants")


class LifecycleError(Exception):
    """The module fails with this message and these fields."""

    def __init__(self, msg: str, **fields):
        super().__init__(msg)
        self.msg, self.fields = msg, fields


def _want(host: Host, p: dict, found: dict) -> dict:
    """The wanted state of the host, from the plan; found: the companions on the host now."""
    plan = p["plan"]
    env_mode = 0o600 if p["secret_env"] else 0o644
    files = {
        os.path.join(layout.UNIT_DIR, layout.UNIT_TEMPLATE): (
            unit_files.render_unit(plan["settings"], p["managed"]),
            0o644,
        ),
        os.path.join(layout.UNIT_DIR, layout.TARGET): (unit_files.render_target(p["managed"]), 0o644),
    }
    # the scripts, and the container policy's code that isaac-sim-policy reads beside them (not run by itself)
    for names, source, mode in (
        (layout.SCRIPTS, "the role's files", 0o755),
        (layout.POLICY_LIB, "plugins/module_utils/hostlib", 0o644),
    ):
        for name in names:
            if name not in p["scripts"]:
                raise LifecycleError(f"scripts: {name} is missing. Fix: pass {source}/{name}.")
            text = p["scripts"][name]
            files[os.path.join(layout.LIBEXEC_DIR, name)] = (text if text.endswith("\n") else text + "\n", mode)
    for unit in plan.get("companion_units", []):
        files[os.path.join(layout.UNIT_DIR, layout.companion_template(unit["name"]))] = (
            unit_files.render_companion_unit(unit, plan["settings"], p["managed"]),
            0o644,
        )
    # templates of companions the plan no longer has: removed once their units are gone
    for name in hostprobe.companion_templates(layout.UNIT_DIR, host.find):
        files.setdefault(os.path.join(layout.UNIT_DIR, layout.companion_template(name)), (None, None))
    instances = {
        inst["id"]: unit_files.render_env(inst, plan, p["image_id"], p["secret_env"], p["managed"])
        for inst in plan["instances"]
    }
    companions = {
        inst["id"]: {
            c["name"]: unit_files.render_companion_env(c, plan, p["managed"]) for c in inst.get("companions", [])
        }
        for inst in plan["instances"]
    }
    gone = []
    if p["remove_others"]:
        gone = [i for i in hostprobe.existing_instances(layout.CONFIG_DIR, _WANTS, host.find) if i not in instances]
    wanted = {
        "files": files,
        "instances": instances,
        "companions": companions,
        "companions_found": found,
        "env_mode": env_mode,
        "remove": gone,
        "purge": p["purge"],
        "data_root": plan["layout"]["data_root"],
        "soak": p["soak_seconds"],
        "held_wait": p.get("held_wait", 0),
        "end_sessions": p.get("end_sessions"),
        "defer_running": p["defer_running"],
        "reserve": plan.get("reserved_ports", []),
        "managed": p["managed"],
    }
    if "firewall" in plan:
        wanted["firewall"] = plan["firewall"]
    return wanted


def _network(host: Host, needed: bool):
    """Our macvlan network as Docker has it now, or None. Without Docker (a fresh host, in check
    mode) there is none; that is an error only when the instances need it."""
    try:
        return network.parse_network(host.network(layout.NETWORK))
    except DockerError as exc:
        if needed:
            raise LifecycleError(f"could not ask Docker for the network {layout.NETWORK}: {exc}") from exc
        return None


def _addressed_instances(host: Host) -> list:
    """Instances whose env file gives them an address of their own: stopped or crash-looping ones
    have no container on the network, and still need it."""
    found = []
    for path in sorted(host.find(os.path.join(layout.CONFIG_DIR, "*"))):
        i = layout.instance_id(layout.ENV_FILE_RE, path)
        if i is None:
            continue
        text = host.read(path)
        if text is not None and layout.parse(text).get(layout.K_ADDRESS):
            found.append(i)
    return found


def _drop_network(host: Host, check: bool):
    """Remove our network when nobody is on it and no instance is set to use it: 'remove',
    'kept' (a container is on it, or an instance is set to use it), or None."""
    found = _network(host, needed=False)
    if not found or not found.get("ours"):
        return None
    if found["containers"] or _addressed_instances(host):
        return "kept"
    if check:
        return "remove"
    rc, _out, err = host.run(network.remove_argv())
    if rc != 0:
        raise LifecycleError(f"could not remove the network {layout.NETWORK}: {err.strip()}")
    return "remove"


def _directories(plan: dict):
    """(paths, uid, gid) of the instances' own directories, owned by the release's container user."""
    paths = [inst["root"] for inst in plan["instances"]] + [d for inst in plan["instances"] for d in inst["dirs"]]
    return paths, plan["uid"], plan["gid"]


def _diff(host: Host, files: dict) -> list:
    out = []
    for path, (text, _mode) in sorted(files.items()):
        before = host.read(path)
        if before != text:
            out.append({"before_header": path, "after_header": path, "before": before or "", "after": text})
    return out


def _apply(host: Host, p: dict, out: dict, found: dict, check: bool, diff: bool) -> dict:
    """action=apply: the plan's directories, network, files and instances; fills `out`."""
    want = _want(host, p, found)
    paths, uid, gid = _directories(p["plan"])
    dir_changes = dirs.wanted_changes(paths, uid, gid, 0o750)
    wanted_net = p["plan"].get("network") or {"mode": network.HOST}
    net_todo = network.action(wanted_net, _network(host, needed=wanted_net["mode"] == network.MACVLAN))
    if net_todo == "conflict":  # the plan refuses it; only a change made since gets here
        raise LifecycleError(
            f"the network {layout.NETWORK} differs from the plan's and is in use; nothing was changed. "
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
                raise LifecycleError(
                    f"could not create the network {layout.NETWORK} ({wanted_net['parent']}, "
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
    shown = _diff(host, want["files"]) if diff else None
    try:
        result = lifecycle.apply(host, want, check=check)
        if (dir_changes or creates) and not applied and not check and not result["deferred"]:
            prepare()
    except OSError as exc:
        raise LifecycleError(f"could not write the host's files: {exc}", **out) from exc
    except firewall.FirewallError as exc:
        raise LifecycleError(str(exc), **out) from exc
    net_done = net_todo if creates else None
    # once every instance is off it (the plan moved them to the host's network)
    if net_todo == "remove" and not result["deferred"] and not result["failed"]:
        net_done = "remove" if check else _drop_network(host, check)
    host_changed = bool(dir_changes or creates or net_done == "remove") and not result["deferred"]
    out.update(
        plan=result["plan"],
        deferred=result["deferred"],
        directories=sorted({path for path, _what in dir_changes}),
        network=None if result["deferred"] else net_done,
        changed=result["changed"] or host_changed,
    )
    if shown:
        out["diff"] = shown
    return result


def _would(p: dict, out: dict) -> dict:
    """Check mode of a day-2 start, stop or remove: each instance asked for would be acted on."""
    out["changed"] = bool(p["ids"])
    return {"done": [{"id": i, "action": p["action"]} for i in p["ids"]], "failed": None, "untouched": []}


def _restart(host: Host, p: dict, out: dict, found: dict, check: bool) -> dict:
    """action=restart: one instance at a time, each ready (and soaked) before the next."""
    result = lifecycle.restart_each(
        host,
        p["ids"],
        p["soak_seconds"],
        check=check,
        companions=found,
        held_wait=p.get("held_wait", 0),
        end_sessions=p.get("end_sessions"),
        data_root=p.get("data_root") or layout.DATA_ROOT,
    )
    out["changed"] = result["changed"]
    return result


def _start(host: Host, p: dict, out: dict, found: dict, check: bool) -> dict:
    """action=start: the instances started together, each that failed reported (left as systemd has it)."""
    if check:
        return _would(p, out)
    out["changed"] = bool(p["ids"])
    result = {"done": [], "failed": None, "failures": [], "untouched": []}
    for i, (ok, reason) in lifecycle.start(host, p["ids"], companions=found).items():
        if ok:
            result["done"].append({"id": i, "action": "start"})
        else:
            result["failures"].append({"id": i, "reason": reason, "reverted": None, "left": "failed"})
    result["failed"] = result["failures"][0] if result["failures"] else None
    return result


def _stop_or_remove(host: Host, p: dict, out: dict, found: dict, check: bool) -> dict:
    """action=stop or remove; the last instance removed takes the network and the reserved ports with it."""
    if check:
        return _would(p, out)
    if p["action"] == "stop":
        lifecycle.stop(host, p["ids"])
    else:
        lifecycle.remove(host, p["ids"], p["purge"], p["data_root"], companions=found)
        # the last instance on it gone (cleanup, scale to 0): the network goes too, and the ports
        out["network"] = _drop_network(host, check)
        if not hostprobe.existing_instances(layout.CONFIG_DIR, _WANTS, host.find):
            try:
                out["reserved_ports"] = lifecycle.reserve(host, [], p["managed"], grow=False)
            except OSError as exc:
                raise LifecycleError(str(exc)) from exc
    out["changed"] = bool(p["ids"]) or out.get("network") == "remove" or bool(out.get("reserved_ports"))
    return {"done": [{"id": i, "action": p["action"]} for i in p["ids"]], "failed": None, "untouched": []}


# The day-2 actions (playbooks/instance.yml, isaac_sim_action): what each does to the instances
# asked for, through lifecycle.py. The module's and the role's choice lists are these
# (tests/unit/test_day2_actions.py).
DAY2 = {"start": _start, "stop": _stop_or_remove, "restart": _restart, "remove": _stop_or_remove}


def _failure_text(failures: list, untouched: list) -> str:
    """The message of the instances that failed (more than one only where they started together):
    each one, why and where it was left, the first as a single failure says it; then what was
    not reached."""
    rest = f"; not reached: {', '.join(layout.container(i) for i in untouched)}" if untouched else ""
    return "; also ".join(_one_failure(failed) for failed in failures) + rest


def _one_failure(failed: dict) -> str:
    """One failed instance: why, and where it was left."""
    if failed.get("reverted") is None:
        back = "it was stopped (there are no earlier settings to go back to)" if failed.get("left") == "stopped" else ""
    elif failed.get("reverted"):
        back = f"it went back to {failed.get('reverted_to')}" + (
            " and is ready again" if failed.get("left") == "running" else ""
        )
    else:
        back = f"going back failed too: {failed.get('revert_error')}"
    return f"{layout.container(failed['id'])}: {failed['reason']}" + (f"; {back}" if back else "")


def call(host: Host, p: dict, check: bool = False, diff: bool = False, lock: str = "", record: str = "") -> dict:
    """The module's result for its parameters `p`; raises LifecycleError with the message and the
    fields of a failed call. lock, record: runlock's files (its own paths when empty)."""
    lock, record = lock or runlock.LOCK, record or runlock.RECORD
    run = p["controller_run"]
    held = run and (runlock.read(lock) or {}).get("id") == run
    if not held or check:
        return _call(host, p, check, diff, run, record)
    host.interrupted = lambda: runlock.gone(run, host.wall(), path=lock)
    # recorded in the lock while it runs: a run that takes over after this one's controller ended waits
    # for it to stop (runlock.decide), never changes the host beside it
    runlock.mark_job(run, os.getpid(), path=lock)
    try:
        return _call(host, p, check, diff, run, record)
    finally:
        runlock.clear_job(run, os.getpid(), path=lock)


def _call(host: Host, p: dict, check: bool, diff: bool, run: str, record: str) -> dict:
    out = dict(changed=False, done=[], failed_instance=None, failed_instances=[], untouched=[], left=[], ended=[])
    found = hostprobe.existing_companions(layout.CONFIG_DIR, host.find)

    if p["action"] == "apply":
        result = _apply(host, p, out, found, check, diff)
    else:
        result = DAY2[p["action"]](host, p, out, found, check)

    # every instance that failed; more than one only where they started together
    failures = result.get("failures") or ([result["failed"]] if result["failed"] else [])
    out.update(
        done=result["done"],
        failed_instance=result["failed"],
        failed_instances=failures,
        untouched=result["untouched"],
        left=result.get("left", []),
        ended=result.get("ended", []),
    )
    if result.get("interrupted"):
        runlock.record(
            {
                "run": run,
                "at": host.wall(),
                "interrupted": result["interrupted"],
                "done": [d["id"] for d in result["done"]],
                "untouched": result["untouched"],
            },
            path=record,
        )
        out["changed"] = out["changed"] or result["changed"]
        raise LifecycleError(
            f"rollout interrupted: {result['interrupted']}; it stopped before "
            f"{', '.join(layout.container(i) for i in result['untouched'])}, which are as they were",
            interrupted=result["interrupted"],
            **out,
        )
    if result["failed"]:
        raise LifecycleError(_failure_text(failures, result["untouched"]), **out)
    return out
