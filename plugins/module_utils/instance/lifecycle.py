# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The one lifecycle of a host's Isaac Sim instances.

Every path that changes running instances comes here: a deploy (apply), a
day-2 start, stop, restart or remove, a scale-down, a cleanup, a rolling
restart and an upgrade. The steps are the same everywhere:

- an instance that is not serving (new, stopped, failed) is started at once,
  all of them together;
- a serving instance whose settings changed is changed one at a time: stop it
  if stuck activating, reset its start counter, restart, wait until ready,
  soak; so a host of N keeps N-1 serving;
- on the first failure the instance goes back to its previous settings (and
  image), the files shared by all instances too, everything after it is left
  as it is, and the failure is reported with the instance and the reason;
  instances started together end together: each one that failed goes back
  (a new one is stopped), each is reported, and the ready ones are done.

The host is reached through a small interface (run, read, write, remove,
mode, exists, sleep, now, wall, find, network) that the module binds to the
real host and the unit tests to a scripted one.
"""

from __future__ import annotations

import glob
import json
import os
import re
import shutil
import subprocess
import time

from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerError, DockerSocket
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import firewall, reserved_ports

_GATE_WORDS = re.compile(
    r"not ready within|stopped before it was ready|went away before it was ready|docker run exited"
)


class Host:
    """The host as the lifecycle sees it. The module fills it with real calls.

    read(path) -> text or None; write(path, text, mode); remove(path) removes a
    file or a tree; mode(path) -> int or None; now() a monotonic clock, wall()
    epoch seconds for the journal; find(pattern) -> the paths a glob pattern
    matches (none unless given); network(name) -> Docker's answer for a network
    (raises DockerError; Docker is not reachable unless given).
    """

    def __init__(
        self, run, read, write, remove, mode, exists, sleep, now, wall, interrupted=None, find=None, network=None
    ):
        self.run, self.read, self.write, self.remove, self.mode = run, read, write, remove, mode
        self.exists, self.sleep, self.now, self.wall = exists, sleep, now, wall
        # why the run that asked for this is gone ("" while it is there): checked between instances
        self.interrupted = interrupted or (lambda: "")
        self.find = find or (lambda _pattern: [])
        self.network = network or _no_docker


def _no_docker(name):
    raise DockerError(f"no Docker to ask for the network {name}")


def bind(module) -> Host:
    """The real host, for a module running on it."""
    return bind_local(lambda argv: module.run_command([module.get_bin_path(argv[0], required=True)] + argv[1:]))


# where a command is looked for after PATH: a service's PATH may lack the sbin directories
SYSTEM_PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin"


def command_path(name: str) -> str | None:
    """The path of command `name`, on PATH or else on SYSTEM_PATH; None where it is on neither."""
    return shutil.which(name) or shutil.which(name, path=SYSTEM_PATH)


def run_process(argv) -> tuple:
    """(rc, stdout, stderr) of a command run without a shell, for a process that is not a module
    (the host's action agent); a command not found is rc 127, as a shell says it."""
    path = command_path(argv[0])
    if not path:
        return 127, "", f"{argv[0]}: not found"
    done = subprocess.run([path] + list(argv[1:]), capture_output=True, text=True, check=False)
    return done.returncode, done.stdout, done.stderr


def bind_local(run=run_process) -> Host:
    """The real host, its commands run by run(argv) -> (rc, stdout, stderr)."""

    def read(path):
        try:
            with open(path) as fh:
                return fh.read()
        except OSError:
            return None

    def write(path, text, mode):
        if path.startswith("/proc/sys/"):  # a kernel setting: written in place, never replaced
            with open(path, "w") as fh:
                fh.write(text)
            return
        directory = os.path.dirname(path)
        os.makedirs(directory, mode=0o755, exist_ok=True)
        tmp = os.path.join(directory, f".{os.path.basename(path)}.tmp")
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
        with os.fdopen(fd, "w") as fh:
            fh.write(text)
        os.chmod(tmp, mode)
        os.replace(tmp, path)

    def remove(path):
        if os.path.isdir(path) and not os.path.islink(path):
            shutil.rmtree(path)
        elif os.path.lexists(path):
            os.unlink(path)

    def mode(path):
        try:
            return os.stat(path).st_mode & 0o777
        except OSError:
            return None

    return Host(
        run,
        read,
        write,
        remove,
        mode,
        os.path.exists,
        time.sleep,
        time.monotonic,
        time.time,
        find=glob.glob,
        network=lambda name: DockerSocket().network(name),
    )


# InvocationID changes with every start: a session end resets NRestarts (isaac-sim-run), so the
# count alone could read the same before and after a restart
PROPS = "Id,ActiveState,SubState,NRestarts,Result,UnitFileState,InvocationID"


def show(host: Host, units, props: str = PROPS) -> dict:
    """{unit: {property: value}} for the given units in one systemctl call ({} for a unit not shown)."""
    units = list(units)
    if not units:
        return {}
    _rc, out, _err = host.run(["systemctl", "show", "-p", props] + units)
    found = layout.parse_shown(out)
    return {u: found.get(u, {}) for u in units}


def states(host: Host, ids) -> dict:
    """{id: {ActiveState, SubState, NRestarts, Result, UnitFileState}} in one systemctl call."""
    ids = list(ids)
    shown = show(host, [layout.unit(i) for i in ids])
    return {i: shown[layout.unit(i)] for i in ids}


def companion_units(companions: dict, ids=None) -> list:
    """Units of the companions {id: [names]} of the instances `ids` (all by default)."""
    return [
        layout.companion_unit(i, name)
        for i, names in sorted(companions.items())
        if ids is None or i in ids
        for name in names
    ]


def leftover_companions(host: Host, wanted: dict) -> list:
    """Failed units of companions no instance has any more (a companion whose first start failed
    and whose instance went back): systemd keeps listing them, and the host degraded, until they
    are reset, whether or not their unit file is still there."""
    _rc, out, _err = host.run(
        ["systemctl", "list-units", "--failed", "--all", "--plain", "--no-legend", "isaac-sim-*@*.service"]
    )
    units = [line.split()[0] for line in out.splitlines() if line.strip()]
    found = [(u, layout.COMPANION_UNIT_RE.match(u)) for u in units]
    return [u for u, m in found if m and m.group(1) not in wanted.get(int(m.group(2)), [])]


def serving(state: dict) -> bool:
    return state.get("ActiveState") == "active"


def _gate_reason(host: Host, unit: str, since: float) -> str:
    """The readiness gate's own words about why the start failed, with the container's last
    lines the gate quoted ("| ..."), else systemd's result."""
    _rc, out, _err = host.run(["journalctl", "-u", unit, "--since", f"@{int(since)}", "-o", "cat", "--no-pager"])
    lines = [line.strip() for line in out.splitlines()]
    for n in range(len(lines) - 1, -1, -1):
        if _GATE_WORDS.search(lines[n]) and not lines[n].startswith("|"):
            quoted = [q[1:].strip() for q in lines[n + 1 :] if q.startswith("|") and not _GATE_WORDS.search(q)]
            return lines[n] + (f" (last lines: {' / '.join(quoted[-3:])})" if quoted else "")
    state = show(host, [unit])[unit]
    said = f"the unit did not start (ActiveState={state.get('ActiveState')}, Result={state.get('Result')})"
    # the start's own last words (isaac-sim-run's: a port held, the container policy's refusal)
    last = [line for line in lines if line and not line.startswith(("event=", "|"))][-2:]
    return said + (f" (last lines: {' / '.join(last)})" if last else "")


def companions_up(host: Host, companions: dict) -> dict:
    """{id: reason or None}: start the companions {id: [names]} of instances that are ready, all
    together (each one's start ends at its own readiness gate); None when all of an instance's are up."""
    units = companion_units(companions)
    out = {i: None for i in companions}
    if not units:
        return out
    since = host.wall()
    # a deliberate start must not count against the crash-loop limit
    host.run(["systemctl", "reset-failed"] + units)
    host.run(["systemctl", "start"] + units)
    shown = show(host, units)
    for i, names in sorted(companions.items()):
        for name in names:
            unit = layout.companion_unit(i, name)
            if out[i] is None and not (serving(shown[unit]) and host.exists(layout.companion_marker(i, name))):
                out[i] = f"its companion {layout.companion_container(i, name)} did not start: " + _gate_reason(
                    host, unit, since - 1
                )
    return out


def _prepare_start(host: Host, ids, state: dict, renew=None):
    """Stop the instances of `renew` (all by default) that are stuck activating, reset every counter."""
    for i in ids if renew is None else [i for i in ids if i in renew]:
        if state.get(i, {}).get("ActiveState") == "activating":
            # a restart would cancel the pending start job and fail; stop it first
            host.run(["systemctl", "stop", layout.unit(i)])
    # a deliberate (re)start must not count against the crash-loop limit
    host.run(["systemctl", "reset-failed"] + [layout.unit(i) for i in ids])


def restart(host: Host, i: int, between=None, companions=()) -> tuple:
    """(ok, reason, seconds): stop + start + ready, as systemd's restart with the readiness gate does it,
    then the instance's companions (names), each up and ready.

    between: called while the instance is stopped (its container gone), before it starts again.
    """
    _prepare_start(host, [i], states(host, [i]))
    start, since = host.now(), host.wall()
    if between is None:
        # PartOf= restarts the companions that run; companions_up starts the others
        rc, _out, _err = host.run(["systemctl", "restart", layout.unit(i)])
    else:
        host.run(["systemctl", "stop", layout.unit(i)])
        between()
        rc, _out, _err = host.run(["systemctl", "start", layout.unit(i)])
    if rc != 0:
        return False, _gate_reason(host, layout.unit(i), since - 1), host.now() - start
    if not host.exists(layout.marker(i)):
        return False, "the unit is active but the readiness gate left no ready marker", host.now() - start
    reason = companions_up(host, {i: list(companions)})[i]
    return reason is None, reason, host.now() - start


def start(host: Host, ids, renew=(), companions=None) -> dict:
    """{id: (ok, reason)}: start instances that are not serving, all at once; each ends ready or failed,
    then the companions ({id: [names]}) of those that are ready.

    An instance already activating (coming back after a Docker restart, say) is waited for, unless
    it is in `renew` (its settings changed): then its start job, on the old settings, is stopped first.
    """
    ids = list(ids)
    if not ids:
        return {}
    _prepare_start(host, ids, states(host, ids), renew=set(renew))
    since = host.wall()
    host.run(["systemctl", "start"] + [layout.unit(i) for i in ids])
    after = states(host, ids)
    out = {}
    for i in ids:
        if serving(after[i]) and host.exists(layout.marker(i)):
            out[i] = (True, None)
        else:
            out[i] = (False, _gate_reason(host, layout.unit(i), since - 1))
    ready = {i: list((companions or {}).get(i, ())) for i in ids if out[i][0]}
    for i, reason in companions_up(host, ready).items():
        if reason:
            out[i] = (False, reason)
    return out


def soak(host: Host, i: int, seconds: float, interval: float = 1.0) -> tuple:
    """(ok, reason): stay active and ready, with the restart count unchanged, for `seconds`."""
    first = states(host, [i])[i]
    base, first_start = first.get("NRestarts", "0"), first.get("InvocationID")
    begin = host.now()
    while True:
        state = first if first is not None else states(host, [i])[i]
        first = None
        elapsed = host.now() - begin
        if state.get("NRestarts", "0") != base or state.get("InvocationID") != first_start:
            return (
                False,
                f"restarted during the soak (NRestarts {base} -> {state.get('NRestarts')}) after {elapsed:.0f} s",
            )
        if not serving(state) or not host.exists(layout.marker(i)):
            return (
                False,
                f"lost readiness during the soak after {elapsed:.0f} s (ActiveState={state.get('ActiveState')})",
            )
        if elapsed >= seconds:
            return True, None
        host.sleep(min(interval, max(0.0, seconds - elapsed)))


def pinned(host: Host, text: str) -> str:
    """An env file pinned to its image id when its tag has moved to another image since it was written."""
    env = layout.parse(text)
    ref, image_id = env.get(layout.K_IMAGE, ""), env.get(layout.K_IMAGE_ID, "")
    # pinned to a digest by its deploy: it runs that digest, whatever the tag does
    if not image_id.startswith("sha256:") or env.get(layout.K_IMAGE_PINNED):
        return text
    rc, out, _err = host.run(["docker", "image", "inspect", "-f", "{{.Id}}", ref])
    if rc == 0 and out.strip() == image_id:
        return text
    line = f"{layout.K_IMAGE}={layout.quote(image_id)}"
    return re.sub(rf"^{layout.K_IMAGE}=.*$", lambda _match: line, text, count=1, flags=re.M)


def stop(host: Host, ids) -> None:
    if ids:
        host.run(["systemctl", "stop"] + [layout.unit(i) for i in ids])


def remove(host: Host, ids, purge=False, data_root=layout.DATA_ROOT, companions=None) -> None:
    """Stop, disable and forget instances and their companions ({id: [names]}); their caches, logs
    and data stay unless purge."""
    ids = list(ids)
    if not ids:
        return
    units = companion_units(companions or {}, ids) + [layout.unit(i) for i in ids]
    host.run(["systemctl", "disable", "--now"] + units)
    for i in ids:
        host.remove(layout.env_file(i))
        for name in (companions or {}).get(i, ()):
            host.remove(layout.companion_env_file(i, name))
        if purge:
            host.remove(layout.data_dir(i, data_root))
    host.run(["systemctl", "reset-failed"] + units)


class _Files:
    """Writes that remember what was there, so a failure can put it back."""

    def __init__(self, host: Host):
        self.host, self.before = host, {}

    def write(self, path, text, mode):
        if path not in self.before:
            self.before[path] = (self.host.read(path), self.host.mode(path))
        self.host.write(path, text, mode)

    def restore(self, paths):
        for path in paths:
            text, mode = self.before.get(path, (None, None))
            if text is None:
                self.host.remove(path)
            else:
                self.host.write(path, text, mode)


def user_of(text) -> str:
    """The container user an env file runs its instance as (docker's --user), "" if none."""
    args = layout.split_args(layout.parse(text or "").get(layout.K_DOCKER_ARGS, ""))
    return next((a.split("=", 1)[1] for a in args if a.startswith("--user=")), "")


def ports_of(text) -> set:
    """(address, port) for each port an env file gives its instance (protocol left out: the safe
    side). The address is the instance's own ("" on the host's network): the same port at two
    addresses is no clash."""
    env = layout.parse(text or "")
    address = env.get(layout.K_ADDRESS, "")
    return {(address, int(v)) for k, v in env.items() if k.startswith(layout.K_PORT_PREFIX) and v.isdigit()}


def _port_text(port) -> str:
    """49100, or 10.0.0.5:49100 for a port at an instance's own address."""
    if isinstance(port, tuple):
        address, number = port
        return f"{address}:{number}" if address else str(number)
    return str(port)


def port_order(old: dict, new: dict, roll: list, start: list) -> tuple:
    """(steps, notes): the order in which to change instances so none starts on a port
    another instance still holds.

    old/new: {id: set of ports} before and after; roll: serving instances to restart one
    at a time; start: instances not serving, to start. steps: [("start", [ids]) or
    ("roll", id) or ("stop", [ids])]. When serving instances block each other in a
    cycle, the blockers are stopped before the instance that needs their ports (the
    host goes below N-1 for that step) and started after: notes say so.
    """
    holding = {i: set(old.get(i, ())) for i in roll}  # serving, still on their old ports

    def blocked(i):
        return {j for j, ports in holding.items() if j != i and ports & new.get(i, set())}

    steps, notes = [], []
    first = [i for i in start if not blocked(i)]
    later = [i for i in start if i not in first]
    if first:
        steps.append(("start", first))
    pending = list(roll)
    while pending:
        free = [i for i in pending if not blocked(i)]
        if free:
            i = free[0]
        else:
            i = min(pending, key=lambda x: (len(blocked(x)), x))
            gone = sorted(blocked(i))
            steps.append(("stop", gone))
            freed = sorted(new[i] & set().union(*(holding[j] for j in gone)))
            notes.append(
                f"{', '.join(layout.container(j) for j in gone)} stopped before {layout.container(i)} to free "
                f"port(s) {', '.join(_port_text(p) for p in freed)}: "
                f"the host is below N-1 until they start again on their new ports"
            )
            for j in gone:
                pending.remove(j)
                holding.pop(j)
                later.append(j)
        pending.remove(i)
        holding.pop(i)
        steps.append(("roll", i))
    if later:
        steps.append(("start", sorted(later)))
    return steps, notes


def _enabled(state: dict) -> bool:
    return state.get("UnitFileState") in ("enabled", "enabled-runtime", "static", "indirect")


def _instance_files(i: int, want: dict) -> dict:
    """{path: text, or None for a file to remove}: the env files of instance i and of its companions."""
    files = {layout.env_file(i): want["instances"][i]}
    wanted = (want.get("companions") or {}).get(i, {})
    for name, text in wanted.items():
        files[layout.companion_env_file(i, name)] = text
    for name in (want.get("companions_found") or {}).get(i, ()):
        if name not in wanted:
            files[layout.companion_env_file(i, name)] = None
    return files


def _names(files: dict, i: int) -> list:
    """The companions an instance's file set has (those with a text)."""
    names = []
    for path, text in files.items():
        match = layout.COMPANION_ENV_RE.match(path.rsplit("/", 1)[-1])
        if text is not None and match and int(match.group(1)) == i:
            names.append(match.group(2))
    return sorted(names)


def reserve(host: Host, ports, managed: str, grow: bool, check=False) -> bool:
    """Keep `ports` out of the host's ephemeral range (reserved_ports.py): in the kernel now, in
    sysctl.d for the next boot. Returns whether anything changed (or would, in check mode)."""
    runtime = host.read(reserved_ports.PROC)
    if runtime is None:  # not Linux's /proc: nothing to keep
        return False
    before = host.read(reserved_ports.CONF)
    value, added = reserved_ports.wanted(runtime, before, ports, grow)
    text = reserved_ports.conf(value, added, managed)
    kernel = value != reserved_ports.parse(runtime)
    changed = kernel or text != before
    if check or not changed:
        return changed
    if text is None:
        host.remove(reserved_ports.CONF)
    elif text != before:
        host.write(reserved_ports.CONF, text, 0o644)
    if kernel:
        try:
            host.write(reserved_ports.PROC, reserved_ports.render(value) + "\n", 0o644)
        except OSError as exc:
            raise OSError(
                f"could not reserve the instances' ports ({reserved_ports.KEY}={reserved_ports.render(value)}): "
                f"{exc}. Fix: a host that is itself a container needs a writable /proc/sys, or the value set "
                f"where it is created (docker run --sysctl {reserved_ports.KEY}=...)"
            ) from exc
    return True


def linger(host: Host, ports, limit_s: float = reserved_ports.LINGER_LIMIT_S) -> set:
    """Wait until no outgoing connection (or its TIME_WAIT) has any of the newly reserved `ports`
    as its source port, up to limit_s. Returns the ports still held then: an instance that
    binds one fails its start and goes back, as any failed start does."""
    deadline = host.now() + limit_s
    while True:
        held = reserved_ports.lingering(
            [host.read("/proc/net/tcp"), host.read("/proc/net/tcp6")],
            ports,
            [host.read("/proc/net/udp"), host.read("/proc/net/udp6")],
        )
        if not held or host.now() >= deadline:
            return held
        host.sleep(1)


def apply(host: Host, want: dict, check=False) -> dict:
    """Bring the host to `want`, never taking more than one serving instance down at a time.

    want: {"files": {path: (text, mode), or (None, None) to remove} shared by every instance
           (units, scripts), "instances": {id: env text}, "companions": {id: {name: env text}},
           "companions_found": {id: [names]} (on the host now), "env_mode": int, "remove": [ids],
           "purge": bool, "data_root": str, "soak": seconds, "defer_running": bool,
           "reserve": [ports] to keep out of the ephemeral range, or None, "managed": str,
           "held_wait": seconds to wait for a run or session to give back an instance that would roll}
    An instance changes when its env file or one of its companions' does; it changes with its
    companions, as one. With defer_running, a host where a serving instance would restart or be
    removed is left as it is (deferred=True): the caller rolls it later, in canary batches.

    An instance lent to a run or a session is waited for up to held_wait, then left on its settings as
    they are ("left", with its holder); the others roll. Returns {"plan", "done", "failed", "untouched",
    "left", "deferred", "changed", ...}; when the apply
    stops at instances that failed, "failures" has one entry for each (more than one only where
    they started together) and "failed" is the first of them.
    """
    desired = {i: _instance_files(i, want) for i in sorted(want["instances"])}
    found = want.get("companions_found") or {}
    gone = sorted(want.get("remove") or [])
    state = states(host, list(desired) + gone)
    all_files = want.get("files", {})
    shared = {p: f for p, f in all_files.items() if f[0] is not None and (host.read(p) != f[0] or host.mode(p) != f[1])}
    stale = [p for p, f in all_files.items() if f[0] is None and host.read(p) is not None]
    current = {i: {path: host.read(path) for path in files} for i, files in desired.items()}
    changed_ids = {i for i in desired if current[i] != desired[i]}
    wanted_companions = {i: _names(files, i) for i, files in desired.items()}
    comp_state = show(host, companion_units(wanted_companions))
    cleared = leftover_companions(host, wanted_companions)
    to_start = [i for i in desired if not serving(state[i])]
    # the target only groups the instances, and the firewall's scripts are the firewall unit's: a new one
    # restarts no instance
    restarting = [
        p
        for p in shared
        if p != os.path.join(layout.UNIT_DIR, layout.TARGET) and os.path.basename(p) not in layout.NOT_RUN_BY_INSTANCES
    ]
    to_roll = [i for i in desired if serving(state[i]) and (i in changed_ids or restarting)]
    to_enable = [i for i in desired if not _enabled(state[i])]
    enable_companions = [
        (i, n)
        for i, names in wanted_companions.items()
        if i not in changed_ids
        for n in names
        if not _enabled(comp_state.get(layout.companion_unit(i, n), {}))
    ]
    # a companion down beside a serving instance that does not change: started, the instance left alone
    revive = {
        i: [n for n in names if not serving(comp_state.get(layout.companion_unit(i, n), {}))]
        for i, names in wanted_companions.items()
        if i not in to_start and i not in to_roll
    }
    revive = {i: names for i, names in revive.items() if names}
    _rc, target_state, _err = host.run(["systemctl", "show", "-p", "UnitFileState", "--value", layout.TARGET])
    # a target enabled before it was wanted by docker.service gets its new link from systemctl enable
    target_enabled = target_state.strip() == "enabled" and host.exists(layout.TARGET_DOCKER_WANT)
    main_env = {i: layout.env_file(i) for i in desired}
    steps, notes = port_order(
        {i: ports_of(current[i][main_env[i]]) for i in desired},
        {i: ports_of(desired[i][main_env[i]]) for i in desired},
        to_roll,
        to_start,
    )
    plan = {
        "files": sorted(shared) + sorted(stale),
        "start": to_start,
        "roll": to_roll,
        "remove": gone,
        "enable": to_enable
        + ([] if target_enabled else [layout.TARGET])
        + [layout.companion_unit(i, n) for i, n in enable_companions],
        "companions": {i: [layout.companion_unit(i, n) for n in names] for i, names in revive.items()},
        "cleared": cleared,
        "order": [f"{kind} {' '.join(map(str, what)) if isinstance(what, list) else what}" for kind, what in steps],
        "notes": notes,
        # why each serving instance would restart, for a person reading a dry run (--check)
        "restart_why": {
            i: "its settings changed"
            if i in changed_ids
            else f"the files every instance runs with changed ({', '.join(os.path.basename(p) for p in restarting)})"
            for i in to_roll
        },
    }
    result = {"plan": plan, "done": [], "failed": None, "untouched": [], "left": [], "ended": [], "deferred": False}
    # who holds each instance that would roll: a dry run says which ones a rollout would leave
    plan["held"] = holders(host, to_roll)
    ports = want.get("reserve")
    managed = want.get("managed", "")
    reserving = ports is not None and reserve(host, ports, managed, grow=False, check=True)
    plan["reserved_ports"] = reserving
    # the firewall (firewall.py): while instances change, the rules of before and after are loaded
    # together; the planned ones alone once every instance runs as planned. Without the key, no firewall
    # is managed at all (a call that is not a deploy's).
    walls = "firewall" in want
    wall = want.get("firewall")
    wall_kept = firewall.state(host).get("model") if walls else None
    wall_todo = walls and not firewall.in_sync(host, wall, managed)
    plan["firewall"] = ("load" if wall else "remove") if wall_todo else None
    # every change but the serving instances' rolls, which may end up left for their holders
    besides_rolls = bool(
        shared or stale or to_start or gone or plan["enable"] or revive or cleared or reserving or wall_todo
    )
    changed = besides_rolls or bool(to_roll)
    if check or not changed:
        result["changed"] = changed
        return result
    # a scale-down that stops serving instances is a change of serving instances: canary batches too
    if want.get("defer_running") and (to_roll or any(serving(state[i]) for i in gone)):
        result.update(changed=False, deferred=True)
        return result

    # a scale-down never takes an instance from the test run or session that holds it: nothing changes
    for i in gone:
        holder = lent_to(host, i)
        if holder is not None:
            result.update(failed=_lent_failure(i, holder, "the scale-down would remove it (nothing was changed)"))
            result["changed"] = False
            return result
    if want.get("prepare"):
        want["prepare"]()
    # before any instance opens a port: the rules of the ports to come, and of those still open
    grown = firewall.merge(wall_kept, wall)
    if wall_todo and wall:
        firewall.load(host, grown, managed)
    # before any instance binds a new port; the old ones stay reserved until the end
    if reserving:
        before = reserved_ports.parse(host.read(reserved_ports.PROC))
        reserve(host, ports, managed, grow=True)
        result["lingering"] = sorted(linger(host, set(ports) - before))
    files = _Files(host)
    # scale-down first: it frees the ports and GPUs of the instances that go
    remove(host, gone, want.get("purge", False), want.get("data_root", layout.DATA_ROOT), found)
    result["removed"] = gone
    if cleared:
        host.run(["systemctl", "reset-failed"] + cleared)
    for path, (text, mode) in shared.items():
        files.write(path, text, mode)
    units_changed = any(p.endswith((".service", ".target")) for p in shared)
    if units_changed:
        host.run(["systemctl", "daemon-reload"])

    def put(i, texts, mode_of):
        """Instance i's file set as `texts`; companions that leave are disabled and stopped
        while their unit file is still there, companions that come are enabled."""
        before = _names({p: host.read(p) for p in texts}, i)
        after = _names(texts, i)
        leaving = [layout.companion_unit(i, n) for n in before if n not in after]
        if leaving:
            host.run(["systemctl", "disable", "--now"] + leaving)
            # a companion whose start failed stays listed as failed after its stop
            host.run(["systemctl", "reset-failed"] + leaving)
        for path, text in texts.items():
            if text is None:
                host.remove(path)
            elif host.read(path) != text:
                files.write(path, text, mode_of(path))
        if after:
            host.run(["systemctl", "enable"] + [layout.companion_unit(i, n) for n in after])

    def write_new(i):
        put(i, desired[i], lambda _path: want["env_mode"])

    def put_back(*ids):
        """Previous settings of the instances `ids` and their companions (and the shared files, once),
        pinned to the previous image. Companions that came with the change leave while their unit
        file is there. A shared file that had no previous version is kept when an instance done
        in this apply runs on it."""
        for i in ids:
            old = {
                path: (pinned(host, text) if path == main_env[i] and text else text)
                for path, text in current[i].items()
            }
            put(i, old, lambda path: files.before.get(path, (None, want["env_mode"]))[1] or want["env_mode"])
        # a shared file new in this apply stays once an instance done in it runs on it (the ready
        # instances of a first deploy): no instance runs on its absence
        back = sorted(p for p in shared if files.before.get(p, (None, None))[0] is not None or not result["done"])
        if back:
            files.restore(back)
            if any(p.endswith((".service", ".target")) for p in back):
                host.run(["systemctl", "daemon-reload"])

    stopped = []  # serving instances stopped to free ports, not started again yet

    def handover(i):
        """With a new container user (4.x root -> 5.x uid 1234), what the old one wrote is handed
        over while the instance is down: after its last write, before the new user's first."""
        old_env = current[i][main_env[i]]
        if old_env is None or user_of(old_env) == user_of(desired[i][main_env[i]]) or not want.get("reown"):
            return None
        return lambda: want["reown"](i)

    def wind_down(first):
        """The apply ends before step `first`: instances stopped for ports come back as they were.
        Returns the instances left as they were."""
        if stopped:
            start(host, stopped, companions={i: _names(current[i], i) for i in stopped})
        later = [w for kind, w in steps[first:] if kind == "roll"]
        return [i for i in later if i not in stopped] + stopped

    def stop_here(failures, n):
        """The failure ends the apply: `failures`, one for each instance that failed (more than one
        only where instances started together), the first of them `failed`."""
        result.update(failed=failures[0], failures=failures, untouched=wind_down(n + 1), changed=True)
        return result

    for n, (kind, what) in enumerate(steps):
        if kind == "stop":
            stop(host, what)
            stopped.extend(what)
            continue
        if kind == "start":
            # not serving: nothing to keep up, so all of them at once
            for i in what:
                if i in changed_ids:
                    write_new(i)
                if handover(i):
                    handover(i)()
            stopped[:] = [i for i in stopped if i not in what]
            renew = set(changed_ids) | (set(what) if shared else set())
            outcome = start(host, what, renew=renew, companions={i: wanted_companions[i] for i in what})
            # started together, so each ends on its own: the ready ones are done and serve, and every
            # one that failed is stopped and goes back (none is left restarting on its new settings)
            failing = [i for i, (ok, _reason) in outcome.items() if not ok]
            for i, (ok, _reason) in outcome.items():
                if ok:
                    result["done"].append({"id": i, "action": "start", "restart_s": 0.0, "soak_s": 0.0})
            if not failing:
                continue
            stop(host, failing)
            put_back(*failing)
            # the ready ones serve: enabled as a start that completes leaves them, so a reboot brings them back
            ready = [i for i in what if i not in failing and i in to_enable]
            if ready:
                host.run(
                    ["systemctl", "enable"]
                    + ([] if target_enabled else [layout.TARGET])
                    + [layout.unit(i) for i in ready]
                )
            failures = []
            for i in failing:
                was_new = current[i][main_env[i]] is None
                failures.append(
                    {
                        "id": i,
                        "reason": outcome[i][1],
                        # a new instance has nothing to go back to; it is stopped
                        "reverted": None if was_new else True,
                        "reverted_to": None if was_new else layout.parse(current[i][main_env[i]]).get(layout.K_IMAGE),
                        "revert_error": None,
                        "left": "stopped",
                    }
                )
            return stop_here(failures, n)
        i = what
        why = host.interrupted()
        if why:
            return interrupt(host, result, why, wind_down(n))
        # a run or a session has it: its settings change after it is given back, never under it
        holder = held_after(
            host,
            i,
            None,
            want.get("held_wait", 0),
            end_sessions=want.get("end_sessions"),
            by=want.get("by", ""),
            ended=result["ended"],
            data_root=want.get("data_root", layout.DATA_ROOT),
        )
        if holder is not None and _in_the_way(i, current, desired, main_env, steps):
            failed = _lent_failure(i, holder, "not changed (a port layout change cannot leave it behind)")
            result.update(failed=failed, untouched=[j for j in wind_down(n) if j != i], changed=True)
            return result
        if holder is not None:
            # left on its files as they are: the next deploy finds it changed and rolls it
            result["left"].append(_left(i, holder))
            continue
        if i in changed_ids:
            write_new(i)
        ok, reason, restart_s = restart(host, i, handover(i), wanted_companions[i])
        soak_start = host.now()
        if ok:
            ok, reason = soak(host, i, want.get("soak", 0))
        soak_s = host.now() - soak_start
        if ok:
            action = "apply" if i in changed_ids else "restart"
            result["done"].append(
                {"id": i, "action": action, "restart_s": round(restart_s, 3), "soak_s": round(soak_s, 3)}
            )
            continue
        put_back(i)
        back, back_reason, _seconds = restart(host, i, companions=_names(current[i], i))
        return stop_here(
            [
                {
                    "id": i,
                    "reason": reason,
                    "reverted": back,
                    "reverted_to": layout.parse(current[i][main_env[i]] or "").get(layout.K_IMAGE),
                    "revert_error": back_reason,
                    "restart_s": round(restart_s, 3),
                    "left": "running" if back else "failed",
                }
            ],
            n,
        )

    if revive:
        for i, reason in companions_up(host, revive).items():
            if reason:
                result.update(
                    failed={"id": i, "reason": reason, "reverted": None, "left": "running"},
                    changed=True,
                )
                return result
            result["done"].append({"id": i, "action": "companions", "restart_s": 0.0, "soak_s": 0.0})
    if plan["enable"]:
        host.run(
            ["systemctl", "enable", layout.TARGET]
            + [layout.unit(i) for i in to_enable]
            + [layout.companion_unit(i, n) for i, n in enable_companions]
        )
    # companion templates no instance uses any more: their units are gone, so now the files
    for path in stale:
        host.remove(path)
    if stale:
        host.run(["systemctl", "daemon-reload"])
    # an instance left for its holder still runs on its old ports: they stay reserved and open
    if reserving and not result["left"]:
        reserve(host, ports, managed, grow=False)
    # every instance runs as planned: the rules of ports no longer open go
    if wall_todo:
        if wall is None:
            firewall.remove(host)
        elif grown != wall and not result["left"]:
            firewall.load(host, wall, managed)
    # a deploy whose only change is an instance left for its holder changed nothing
    result["changed"] = bool(result["done"]) or besides_rolls
    return result


def _in_the_way(i: int, current: dict, desired: dict, main_env: dict, steps: list) -> bool:
    """Whether instance i, left on its ports as they are, would hold a port another instance is
    moving to, or the roll's order stops instances to free ports: a port layout change around it."""
    if any(kind == "stop" for kind, _what in steps):
        return True
    kept = ports_of(current[i][main_env[i]])
    wanted = set()
    for j in desired:
        if j != i:
            wanted |= ports_of(desired[j][main_env[j]])
    return bool(kept & wanted)


def journal(host: Host, line: str) -> None:
    """A line of the lifecycle's in the host's journal (tag isaac-sim-lifecycle)."""
    host.run(["logger", "-t", "isaac-sim-lifecycle", line])


def interrupt(host: Host, result: dict, why: str, left: list) -> dict:
    """Stop before the next instance: the one in hand is ready or back, the rest as they were;
    said in the journal, where the next run and a person find it."""
    done = [d["id"] for d in result["done"]]
    said = ", ".join(layout.container(i) for i in done) or "none"
    rest = ", ".join(layout.container(i) for i in left) or "none"
    journal(host, f"rollout interrupted: {why}; done: {said}; left as they were: {rest}")
    result.update(interrupted=why, untouched=list(left), changed=bool(done) or result.get("changed", False))
    return result


def _lent_failure(i: int, holder: str, what: str) -> dict:
    """The failure of a step that would touch instance i while a test run or a person's session has it."""
    if layout.SESSION_RE.match(holder):
        # named as the door names it: session <id>, the holder's name less its prefix
        said, its = f"held by session {holder.partition('-')[2]}", "session"
    else:
        said, its = f"lent to test run {holder}", "run"
    return {
        "id": i,
        "reason": f"{what}, and it is {said}, which it serves until the {its} ends. "
        f"Fix: run again once the {its} is over",
        "reverted": None,
        "left": "running",
    }


def _loan(host: Host, i: int) -> tuple:
    """(run, pid) of instance i's loan; (None, None) when it is not lent."""
    if not host.exists(layout.lent_marker(i)):
        return None, None
    words = (host.read(f"{layout.lent_marker(i)}/run") or "").split()
    pid = int(words[1]) if len(words) > 1 and words[1].isdigit() else None
    return (words[0] if words else "a run"), pid


def lent_to(host: Host, i: int) -> str | None:
    """The run instance i is lent to, or None."""
    return _loan(host, i)[0]


def holders(host: Host, ids, borrower=None) -> dict:
    """{id: holder} of the instances among ids that a run or session other than `borrower` holds."""
    return {i: h for i in ids for h in [lent_to(host, i)] if h is not None and h != borrower}


def held_after(
    host: Host,
    i: int,
    borrower=None,
    wait_s: float = 0.0,
    interval: float = 1.0,
    end_sessions=None,
    by: str = "",
    ended=None,
    data_root: str = layout.DATA_ROOT,
) -> str | None:
    """Who still holds instance i after waiting up to wait_s for them to give it back; None once it is
    free (or held by `borrower`). A loan whose runner is gone is waited for as any other: the next run
    that wants the instance ends it, never a restart of ours under it.

    end_sessions: seconds of warning after which a person's session (front/pool.py) that holds it is
    ended for this rollout: its marker says when and by whom (the host's status shows it, the door warns
    the person), and at that time its claim ends here (None: the instance rolls, restarted as the others;
    the door sees the claim gone; `ended`, a list, gets {id, holder}). A test run is never ended so. None:
    sessions are waited for as runs are. The session's Documents are moved aside for it first
    (take_files, under data_root); where they cannot be, its claim is not ended: the instance is left for
    it (its holder returned, the warning taken back, the reason in the journal), so no one else gets them."""
    deadline = host.now() + max(0.0, float(wait_s or 0))
    ends_at = None
    while True:
        holder = lent_to(host, i)
        if holder is None or holder == borrower:
            return None
        if end_sessions is not None and layout.SESSION_RE.match(holder):
            if ends_at is None:
                ends_at = host.now() + max(0.0, float(end_sessions))
                notice = {"at": round(host.wall() + max(0.0, float(end_sessions)), 3), "by": by or "an operator"}
                host.write(ending_marker(i), json.dumps(notice) + "\n", 0o644)
            if host.now() >= ends_at:
                try:
                    take_files(host, i, holder, data_root)
                except OSError as exc:
                    host.remove(ending_marker(i))
                    journal(host, f"{layout.container(i)} left for {holder}: {exc}")
                    return holder
                unlend(host, i, holder)
                if ended is not None:
                    ended.append(_left(i, holder))
                return None
        elif host.now() >= deadline:
            return holder
        # the controller gone (Ctrl-C, killed) ends the wait too: the rollout then stops at its next step
        if host.interrupted():
            if ends_at is not None:
                host.remove(ending_marker(i))  # the session goes on: nobody ends it now
            return holder
        host.sleep(interval)


def ending_marker(i: int) -> str:
    """In a session's loan marker: when a rollout ends it, and by whom (JSON {at, by})."""
    return f"{layout.lent_marker(i)}/ending"


def _left(i: int, holder: str) -> dict:
    """An instance a rollout left as it was for the run or session that holds it."""
    return {"id": i, "holder": holder}


def _mark(host: Host, i: int, run: str, pid=None) -> tuple:
    rc, _out, err = host.run(["mkdir", layout.lent_marker(i)])
    if rc == 0:
        host.write(f"{layout.lent_marker(i)}/run", f"{run}\n{pid or ''}\n", 0o644)
    return rc == 0, err


class DrainedError(Exception):
    """The host is drained (the fleet API's drain): it takes no new claim."""


def drained(host: Host) -> str:
    """Who drained the host and when, in words; "" when it is not drained."""
    text = host.read(layout.DRAINED)
    if text is None:
        return ""
    try:
        said = json.loads(text)
        return f"by {said.get('by') or '?'} at {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime(float(said['at'])))}"
    except (ValueError, TypeError, KeyError, AttributeError):
        return "(its record unreadable)"


def lend(
    host: Host,
    i: int,
    run: str,
    wait_s: float = 0.0,
    interval: float = 1.0,
    pid=None,
    companions=None,
    data_root: str = layout.DATA_ROOT,
):
    """Lend instance i to `run` (its runner's process `pid`), waiting up to wait_s for the run
    that has it to give it back. Returns None once lent, else the run that still has it. A loan
    whose runner's process is gone is ended first, as its runner would have (restart, then free).
    A lent instance is restarted by no one but its borrower's give_back. A drained host lends
    nothing (DrainedError); what it lent before goes on."""
    why = drained(host)
    if why:
        raise DrainedError(
            f"the host is drained ({why}): it takes no new claim, and {layout.container(i)} is not lent. Fix: "
            "undrain it (POST /api/hosts/HOST/undrain on the front door), or run on another host."
        )
    deadline = host.now() + wait_s
    while True:
        ok, err = _mark(host, i, run, pid)
        if ok:
            return None
        holder, holder_pid = _loan(host, i)
        if holder is None:
            ok, err = _mark(host, i, run, pid)  # given back in between
            if ok:
                return None
            if not host.exists(layout.lent_marker(i)):
                raise OSError(f"cannot lend {layout.container(i)}: {err.strip()}")
        elif holder_pid and not host.exists(f"/proc/{holder_pid}"):
            give_back(host, i, holder, companions, data_root)
            if lent_to(host, i) != holder:
                continue
            # still its holder's (its files could not be moved aside): waited for as a live loan
        if host.now() >= deadline:
            return lent_to(host, i) or "a run"
        host.sleep(interval)


class FilesError(OSError):
    """A session's files could not be moved aside: the reason names the path and the fix."""


def _stat(host: Host, *paths) -> list:
    """[(uid, gid, mode, device, mount point, type)] of each path itself (a link is not followed), or
    FilesError naming what stat said."""
    # two lines a path: the type ("regular file") and the mount point may have spaces
    rc, out, err = host.run(["stat", "--printf", "%u %g %a %d %F\n%m\n"] + list(paths))
    lines = out.split("\n")
    if rc != 0 or len(lines) != 2 * len(paths) + 1:
        raise FilesError(f"stat {' '.join(paths)}: {(err or out).strip() or f'exit {rc}'}")
    found = []
    for n in range(len(paths)):
        uid, gid, mode, dev, kind = lines[2 * n].split(" ", 4)
        found.append((uid, gid, mode, dev, lines[2 * n + 1], kind))
    return found


def _fresh_documents(host: Host, docs: str, like: tuple) -> None:
    """An empty Documents directory with the owner, group and mode of the one moved aside: the container
    user must write it (Docker would make a missing bind source root's)."""
    uid, gid, mode = like[:3]
    rc, out, err = host.run(["install", "-d", "-o", uid, "-g", gid, "-m", mode, docs])
    if rc != 0:
        raise FilesError(
            f"could not make an empty {docs} again (owner {uid}:{gid}, mode {mode}): {(err or out).strip()}. "
            "Fix: make it by hand with that owner and mode, then give the instance back again"
        )


def take_files(host: Host, i: int, holder: str, data_root: str = layout.DATA_ROOT) -> str | None:
    """Move instance i's Documents aside for the session `holder`, so the next person never sees them:
    the directory is renamed, whole, to layout.files_dir(holder) (on the same filesystem: root never
    reads, copies or follows anything inside it), then an empty one with the same owner, group and mode
    takes its place. Returns the stash's path; None when there was nothing to move (a test run's holder,
    no Documents directory, or an empty one: moved all the same, then removed if still empty, so a file the
    person's container writes meanwhile goes with them).

    Again after a crash between the two steps (no Documents, the stash there), it only makes the empty
    directory. It never writes over a stash: one the front door has not taken yet stays, and this one
    goes beside it, files_dir(holder).2, .3 (the agent's GET /files merges them, the newest first).
    A failure raises FilesError: the caller must not give the instance to anyone while its Documents
    may still hold this person's files."""
    if not isinstance(holder, str) or not layout.SESSION_RE.match(holder):
        return None
    docs = layout.documents_dir(i, data_root)
    root = os.path.join(data_root, layout.FILES_DIR)
    stashes = []
    nth = layout.files_stash(holder, 1, data_root)
    while host.exists(nth):
        stashes.append(nth)
        nth = layout.files_stash(holder, len(stashes) + 1, data_root)
    if not host.exists(docs):
        if not stashes:
            return None
        # moved before a crash: the newest stash is that directory, with its owner and mode
        _fresh_documents(host, docs, _stat(host, stashes[-1])[0])
        return stashes[-1]
    # only root may enter: a stash is the front door's to take, through the agent
    rc, out, err = host.run(["install", "-d", "-m", "0700", root])
    if rc != 0:
        raise FilesError(f"could not make {root}: {(err or out).strip()}. Fix: make it (root's, mode 0700)")
    old, where = _stat(host, docs, root)
    if old[5] != "directory":
        raise FilesError(f"{docs} is a {old[5]}, not a directory; left as it is. Fix: look at it, remove it by hand")
    # a rename only: mv copies across filesystems (as root, inside the person's tree), and that it must not
    if old[3:5] != where[3:5]:
        raise FilesError(
            f"{docs} (mount {old[4]}) and {root} (mount {where[4]}) are not on one filesystem, so its files "
            f"cannot be moved aside by a rename. Fix: keep {data_root} on one filesystem"
        )
    stash = layout.files_stash(holder, len(stashes) + 1, data_root)
    # -T: onto that name, never into a directory of that name; a non-empty one there makes it fail
    rc, out, err = host.run(["mv", "-T", docs, stash])
    if rc != 0:
        raise FilesError(
            f"could not move {docs} to {stash}: {(err or out).strip()}. Fix: free disk space or the name, "
            "then give the instance back again"
        )
    _fresh_documents(host, docs, old)
    # empty (the fresh one of a give-back done before): no stash of nothing. rmdir removes an empty
    # directory only, so whatever the container wrote into it after the rename stays
    rc, _out, _err = host.run(["rmdir", stash])
    return None if rc == 0 else stash


def unlend(host: Host, i: int, run: str) -> None:
    """End a loan that nothing ran on: free as it was, no restart."""
    if lent_to(host, i) == run:
        host.remove(layout.lent_marker(i))


def give_back(host: Host, i: int, run: str, companions=None, data_root: str = layout.DATA_ROOT) -> str | None:
    """The end of a loan, in this order: a session's Documents moved aside for it (take_files), instance
    i restarted clean, ready, then free, so the next borrower never gets what the last one left. Returns
    why the restart failed (the instance is free all the same: a failed instance is not ready, so it is
    not lent again).

    When a session's files cannot be moved aside, the instance is restarted all the same (the person's
    container ends) but stays lent to `run`: nobody else is lent what may still hold their files, and
    nothing of theirs is removed. The reason, which names the path and the fix, is returned; the same
    give_back again, once that is fixed, finishes it."""
    holder = lent_to(host, i)
    if holder != run:
        return f"{layout.container(i)} is lent to {holder or 'no run'}, not to {run}; left alone"
    kept = None
    try:
        take_files(host, i, run, data_root)
    except OSError as exc:
        kept = str(exc)
    outcome = restart_each(host, [i], 0, companions=companions, borrower=run, data_root=data_root)
    failed = outcome["failed"]["reason"] if outcome["failed"] else None
    if kept is not None:
        journal(host, f"{layout.container(i)} stays lent to {run}: {kept}")
        return f"{kept}; {layout.container(i)} stays lent to {run}" + (
            f" (its restart failed: {failed})" if failed else ""
        )
    host.remove(layout.lent_marker(i))
    return failed


def restart_each(
    host: Host,
    ids,
    soak_seconds: float,
    check=False,
    companions=None,
    borrower=None,
    held_wait: float = 0.0,
    end_sessions=None,
    by: str = "",
    data_root: str = layout.DATA_ROOT,
) -> dict:
    """A rolling restart of a host: each instance in turn restarted, ready and soaked, with its
    companions ({id: [names]}).

    An instance that fails is restarted once more with the same settings (there is
    nothing older to go back to) and the restart stops there. An instance lent to a run
    other than `borrower` is waited for up to held_wait seconds, then left as it is
    ("left", with its holder) and the restart goes on with the next; one a person's session holds is
    ended after end_sessions seconds of warning where that is given (held_after; its Documents under
    data_root moved aside for it first).
    """
    ids = list(ids)
    result = {"done": [], "failed": None, "untouched": [], "left": [], "ended": [], "changed": bool(ids)}
    if check:
        result["left"] = [_left(i, h) for i, h in holders(host, ids, borrower).items()]
        left = {x["id"] for x in result["left"]}
        result["done"] = [{"id": i, "action": "restart", "restart_s": 0.0, "soak_s": 0.0} for i in ids if i not in left]
        return result
    for n, i in enumerate(ids):
        why = host.interrupted()
        if why:
            return interrupt(host, result, why, ids[n:])
        holder = held_after(
            host, i, borrower, held_wait, end_sessions=end_sessions, by=by, ended=result["ended"], data_root=data_root
        )
        if holder is not None:
            result["left"].append(_left(i, holder))
            continue
        text = host.read(layout.env_file(i))
        if text is None:
            result["failed"] = {
                "id": i,
                "reason": f"{layout.env_file(i)} is missing (not deployed here)",
                "reverted": None,
            }
            result["untouched"] = ids[n + 1 :]
            return result
        names = (companions or {}).get(i, ())
        ok, reason, restart_s = restart(host, i, companions=names)
        soak_start = host.now()
        if ok:
            ok, reason = soak(host, i, soak_seconds)
        if ok:
            result["done"].append(
                {
                    "id": i,
                    "action": "restart",
                    "restart_s": round(restart_s, 3),
                    "soak_s": round(host.now() - soak_start, 3),
                }
            )
            continue
        # the tag may have moved since the instance started: back to the image it ran
        if pinned(host, text) != text:
            host.write(layout.env_file(i), pinned(host, text), host.mode(layout.env_file(i)) or 0o600)
        back, back_reason, _seconds = restart(host, i, companions=names)
        result["failed"] = {
            "id": i,
            "reason": reason,
            "reverted": back,
            "reverted_to": layout.parse(text).get(layout.K_IMAGE),
            "revert_error": back_reason,
            "restart_s": round(restart_s, 3),
        }
        result["untouched"] = ids[n + 1 :]
        return result
    result["changed"] = bool(result["done"]) or bool(result["failed"])
    return result


def summary(outcomes: dict, targets: list, stopped_on: str | None = None) -> list:
    """Lines for a person: what was rolled, reverted, untouched and left for a run or session that holds
    it, and why the rollout stopped.

    outcomes: {host: isaac_sim_lifecycle result (success or failure), or {} when the host was not reached}
    """
    rolled, unchanged, reverted, untouched, left, ended, why = [], [], [], [], [], [], None
    for host in targets:
        out = outcomes.get(host)
        if not out:
            untouched.append(f"{host}: every instance (not reached)")
            continue
        moved = [str(d["id"]) for d in out.get("done", []) if d.get("action") != "unchanged"]
        if moved:
            rolled.append(f"{host}: " + ", ".join(layout.container(i) for i in moved))
        elif not out.get("failed") and not out.get("left"):
            unchanged.append(host)
        # every instance that failed (several where they started together); older results name one
        failures = out.get("failed_instances") or ([out["failed_instance"]] if out.get("failed_instance") else [])
        for failed in failures:
            if failed.get("reverted") is None:
                state = "not started, stopped" if failed.get("left") == "stopped" else "not changed"
            elif failed.get("reverted"):
                state = f"back on {failed.get('reverted_to')}" + (", ready" if failed.get("left") != "stopped" else "")
            else:
                state = f"REVERT FAILED: {failed.get('revert_error')}"
            reverted.append(f"{host}: {layout.container(failed['id'])} ({failed.get('reason')}) - {state}")
        if failures:
            why = "; ".join(f"{layout.container(f['id'])} on {host}: {f.get('reason')}" for f in failures)
        elif out.get("failed"):
            # a failure of no one instance: the lock, the host's files, or a rollout interrupted
            # after some instances were done (their names are in rolled)
            why = why or f"{host}: {out.get('msg')}"
        if out.get("untouched"):
            untouched.append(f"{host}: " + ", ".join(layout.container(i) for i in out["untouched"]))
        if out.get("left"):
            held = ", ".join(f"{layout.container(x['id'])} (held by {x['holder']})" for x in out["left"])
            left.append(f"{host}: {held}")
        if out.get("ended"):
            ended.append(f"{host}: " + ", ".join(f"{layout.container(x['id'])} ({x['holder']})" for x in out["ended"]))
    lines = ["rolled: " + ("; ".join(rolled) or "none")]
    if unchanged:
        lines.append("already current: " + ", ".join(unchanged))
    lines.append("reverted: " + ("; ".join(reverted) or "none"))
    lines.append("untouched: " + ("; ".join(untouched) or "none"))
    if left:
        # not a failure: each runs as it was until its holder gives it back; the next rollout rolls it
        lines.append("left for their holders: " + "; ".join(left))
    if ended:
        # the operator asked for it (isaac_sim_rollout_end_sessions): each holder was warned first
        lines.append("sessions ended for this rollout: " + "; ".join(ended))
    if stopped_on or why:
        lines.append(f"stopped: {why or stopped_on}")
    else:
        lines.append("completed: every host rolled")
    return lines
