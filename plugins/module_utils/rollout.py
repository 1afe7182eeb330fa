# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Roll a host's instances one at a time: apply, restart, ready, soak, or revert.

One call per host does the whole sequence, so a rollout pays Ansible's task
overhead once per host and not per step per instance. The host is reached
through a small interface (run, read, write, exists, sleep, now) that the
module binds to the real host and the unit tests bind to a scripted one.
"""

from __future__ import annotations

import os
import re


def unit(i: int) -> str:
    return f"isaac-sim@{i}.service"


class Host:
    """The host as the rollout sees it. The module fills it with real calls.

    read(path) -> text or None; write(path, text, mode); mode(path) -> int or None;
    now() a monotonic clock for durations, wall() epoch seconds for the journal.
    """

    def __init__(self, run, read, write, mode, exists, sleep, now, wall):
        self.run, self.read, self.write, self.mode = run, read, write, mode
        self.exists, self.sleep, self.now, self.wall = exists, sleep, now, wall


class Paths:
    def __init__(self, config_dir="/etc/isaac-sim", run_dir="/run/isaac-sim", record_dir="/var/lib/isaac-sim/rollout"):
        self.config_dir, self.run_dir, self.record_dir = config_dir, run_dir, record_dir

    def env(self, i):
        return os.path.join(self.config_dir, f"instance-{i}.env")

    def marker(self, i):
        return os.path.join(self.run_dir, f"instance-{i}.ready")

    def record(self, i):
        return os.path.join(self.record_dir, f"instance-{i}.env")


def env_value(text: str, key: str) -> str:
    match = re.search(rf"^{re.escape(key)}=(.*)$", text or "", re.M)
    if not match:
        return ""
    value = match.group(1).strip()
    if len(value) >= 2 and value[0] == value[-1] == '"':
        value = re.sub(r"\\(.)", r"\1", value[1:-1])
    return value


def unit_state(host: Host, i: int) -> dict:
    _, out, _ = host.run(["systemctl", "show", "-p", "ActiveState,SubState,NRestarts,Result", unit(i)])
    return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)


def _gate_reason(host: Host, i: int, since: float) -> str:
    """The readiness gate's own words about why the start failed, else systemd's result."""
    _, out, _ = host.run(["journalctl", "-u", unit(i), "--since", f"@{int(since)}", "-o", "cat", "--no-pager"])
    for line in reversed(out.splitlines()):
        if re.search(r"not ready within|stopped before it was ready|went away before it was ready", line):
            return line.strip()
    state = unit_state(host, i)
    return f"the unit did not start (ActiveState={state.get('ActiveState')}, Result={state.get('Result')})"


def restart(host: Host, paths: Paths, i: int) -> tuple:
    """(ok, reason, seconds): stop + start + ready, as systemd's restart with the readiness gate does it."""
    if unit_state(host, i).get("ActiveState") == "activating":
        # a restart would cancel the pending start job and fail; stop it first
        host.run(["systemctl", "stop", unit(i)])
    # a deliberate restart must not count against the crash-loop limit
    host.run(["systemctl", "reset-failed", unit(i)])
    start, since = host.now(), host.wall()
    rc, _, err = host.run(["systemctl", "restart", unit(i)])
    seconds = host.now() - start
    if rc != 0:
        return False, _gate_reason(host, i, since - 1), seconds
    if not host.exists(paths.marker(i)):
        return False, "the unit is active but the readiness gate left no ready marker", seconds
    return True, None, seconds


def soak(host: Host, paths: Paths, i: int, seconds: float, interval: float = 1.0) -> tuple:
    """(ok, reason): stay active and ready, with the restart count unchanged, for `seconds`."""
    first = unit_state(host, i)
    base = first.get("NRestarts", "0")
    start = host.now()
    while True:
        state = first if first is not None else unit_state(host, i)
        first = None
        elapsed = host.now() - start
        if state.get("NRestarts", "0") != base:
            return (
                False,
                f"restarted during the soak (NRestarts {base} -> {state.get('NRestarts')}) after {elapsed:.0f} s",
            )
        if state.get("ActiveState") != "active" or not host.exists(paths.marker(i)):
            return (
                False,
                f"lost readiness during the soak after {elapsed:.0f} s (ActiveState={state.get('ActiveState')})",
            )
        if elapsed >= seconds:
            return True, None
        host.sleep(min(interval, max(0.0, seconds - elapsed)))


def record(host: Host, paths: Paths, ids) -> dict:
    """Keep each instance's env file (its image and configuration) for a revert: {id: image reference and id}."""
    recorded = {}
    for i in ids:
        text = host.read(paths.env(i))
        if text is None:
            continue
        # the record keeps the original's mode (a file with secrets stays 0600); the directory is 0700
        host.write(paths.record(i), text, host.mode(paths.env(i)) or 0o600)
        recorded[i] = {"image": env_value(text, "ISAAC_SIM_IMAGE"), "image_id": env_value(text, "ISAAC_SIM_IMAGE_ID")}
    return recorded


def _pinned(host: Host, text: str) -> str:
    """The recorded env file, pinned to its image id when its tag has moved to another image since."""
    ref, image_id = env_value(text, "ISAAC_SIM_IMAGE"), env_value(text, "ISAAC_SIM_IMAGE_ID")
    if not image_id.startswith("sha256:"):
        return text
    rc, out, _ = host.run(["docker", "image", "inspect", "-f", "{{.Id}}", ref])
    if rc == 0 and out.strip() == image_id:
        return text
    return re.sub(r"^ISAAC_SIM_IMAGE=.*$", f'ISAAC_SIM_IMAGE="{image_id}"', text, count=1, flags=re.M)


def revert(host: Host, paths: Paths, i: int, previous: str) -> tuple:
    """(ok, reason, image): bring the instance back to its recorded env file and wait until it is ready."""
    recorded = host.read(paths.record(i))
    mode = host.mode(paths.record(i)) if recorded is not None else host.mode(paths.env(i))
    text = _pinned(host, recorded if recorded is not None else previous)
    if text != host.read(paths.env(i)):
        host.write(paths.env(i), text, mode or 0o600)
    ok, reason, _ = restart(host, paths, i)
    return ok, reason, env_value(text, "ISAAC_SIM_IMAGE")


def roll(host: Host, paths: Paths, instances: list, soak_seconds: float, env_mode=0o644, check=False) -> dict:
    """Roll each instance in turn; stop at the first that fails, after reverting it.

    instances: [{"id": i, "env": new env file text, or None to restart as is}]
    env_mode: mode of a new env file (the role's choice: 0600 when it holds secrets).
    """
    done, failed = [], None
    for n, inst in enumerate(instances):
        i = inst["id"]
        current = host.read(paths.env(i))
        if current is None:
            # nothing was changed on it, so there is nothing to revert
            failed = {"id": i, "reason": f"{paths.env(i)} is missing (not deployed here)", "reverted": None}
            untouched = [x["id"] for x in instances[n + 1 :]]
            break
        new = inst.get("env")
        if new is not None and new == current:
            done.append({"id": i, "action": "unchanged", "restart_s": 0.0, "soak_s": 0.0})
            continue
        action = "restart" if new is None else "apply"
        if check:
            done.append({"id": i, "action": action, "restart_s": 0.0, "soak_s": 0.0})
            continue
        if new is not None:
            host.write(paths.env(i), new, env_mode)
        ok, reason, restart_s = restart(host, paths, i)
        soak_start = host.now()
        if ok:
            ok, reason = soak(host, paths, i, soak_seconds)
        soak_s = host.now() - soak_start
        if ok:
            done.append({"id": i, "action": action, "restart_s": round(restart_s, 3), "soak_s": round(soak_s, 3)})
            continue
        back, back_reason, image = revert(host, paths, i, current)
        failed = {
            "id": i,
            "reason": reason,
            "reverted": back,
            "reverted_to": image,
            "revert_error": back_reason,
            "restart_s": round(restart_s, 3),
        }
        untouched = [x["id"] for x in instances[n + 1 :]]
        break
    else:
        untouched = []
    return {
        "done": done,
        "failed": failed,
        "untouched": untouched,
        "changed": any(d["action"] != "unchanged" for d in done) or failed is not None,
    }


def summary(outcomes: dict, targets: list, stopped_on: str | None = None) -> list:
    """Lines for a person: what was upgraded, reverted and untouched, and why the rollout stopped.

    outcomes: {host: isaac_sim_rollout result (success or failure), or None when the host was not reached}
    """
    upgraded, unchanged, reverted, untouched, why = [], [], [], [], None
    for host in targets:
        out = outcomes.get(host)
        if not out:
            untouched.append(f"{host}: every instance (not reached)")
            continue
        moved = [str(d["id"]) for d in out.get("done", []) if d.get("action") != "unchanged"]
        same = [str(d["id"]) for d in out.get("done", []) if d.get("action") == "unchanged"]
        if moved:
            upgraded.append(f"{host}: " + ", ".join(f"isaac-sim-{i}" for i in moved))
        if same:
            unchanged.append(f"{host}: " + ", ".join(f"isaac-sim-{i}" for i in same))
        failed = out.get("failed_instance")
        if failed:
            if failed.get("reverted") is None:
                state = "not changed"
            elif failed.get("reverted"):
                state = f"back on {failed.get('reverted_to')}, ready"
            else:
                state = f"REVERT FAILED: {failed.get('revert_error')}"
            reverted.append(f"{host}: isaac-sim-{failed['id']} ({failed.get('reason')}) - {state}")
            why = f"isaac-sim-{failed['id']} on {host}: {failed.get('reason')}"
        elif out.get("failed") and not out.get("done"):
            why = why or f"{host}: {out.get('msg')}"
        if out.get("untouched"):
            untouched.append(f"{host}: " + ", ".join(f"isaac-sim-{i}" for i in out["untouched"]))
    lines = ["rolled: " + ("; ".join(upgraded) or "none")]
    if unchanged:
        lines.append("already current: " + "; ".join(unchanged))
    lines.append("reverted: " + ("; ".join(reverted) or "none"))
    lines.append("untouched: " + ("; ".join(untouched) or "none"))
    if stopped_on or why:
        lines.append(f"stopped: {why or stopped_on}")
    else:
        lines.append("completed: every host rolled")
    return lines
