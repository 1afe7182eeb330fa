# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
"""One run at a time per host: every playbook that changes instances holds the host's lock from
before it plans until it ends, so two deploys never interleave their settings on one host.

The lock is a JSON file under /run/lock (a reboot ends every run, and takes the file with it;
cleanup.yml, which empties /run/isaac-sim, leaves it to the run that holds it). Its
read-decide-write is one critical section under flock(2) on a guard file, so two runs that
find it free, or stale, at the same moment never both take it. The holder is a playbook run:
the controller's host name, the ansible-playbook process and its start time.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import threading
import time

from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout

LOCK = "/run/lock/isaac-sim.json"
GUARD = "/run/lock/.isaac-sim.guard"
# what the last rollout step on this host did, for the run that comes after an interrupted one
RECORD = "/run/lock/isaac-sim.rollout.json"
# a lifecycle call's controller renews the lock every few seconds while it waits (the action
# plugin isaac_sim_lifecycle); silent this long, the controller is taken for gone
HEARTBEAT_LIMIT_S = 30
# agent: the action id where the holder is the host's action agent (agent.py), not a playbook run
HOLDER_KEYS = ("id", "user", "controller", "pid", "started", "play", "agent")


def request_options(holder_required: bool) -> dict:
    """The argument spec of a lock request: isaac_sim_lock's, and isaac_sim_plan's lock option."""
    return dict(
        holder=dict(type="dict", required=holder_required),
        stale_after=dict(type="int", default=3600),
        break_lock=dict(type="bool", default=False),
        dead=dict(type="str", default=""),
        wait=dict(type="int", default=0),
    )


def holder_text(holder: dict, now: float) -> str:
    """Who holds the lock and since when, in a person's words."""
    since = float(holder.get("since") or 0)
    stamp = time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime(since))
    minutes = max(0, int(now - since)) // 60
    if holder.get("agent"):
        return (
            f"{holder.get('user') or '?'} through the fleet API (action {holder['agent']}: "
            f"{holder.get('play') or '?'}) since {stamp} ({minutes} min ago)"
        )
    play = f", play {holder['play']!r}" if holder.get("play") else ""
    return (
        f"{holder.get('user') or '?'} on {holder.get('controller') or '?'} "
        f"(ansible-playbook pid {holder.get('pid') or '?'}{play}) since {stamp} ({minutes} min ago)"
    )


def decide(current: dict | None, me: dict, now: float, stale_after: int, break_lock=False, dead=""):
    """('take', note) when this run may hold the lock; ('held', who) while another run holds it.

    dead: the id of a holder the controller found gone (its ansible-playbook process ended)."""
    if current is None:
        return "take", ""
    if not isinstance(current, dict) or not current.get("id"):
        return "take", "the lock file was unreadable; it was replaced"
    if current["id"] == me["id"]:
        return "take", ""
    who = holder_text(current, now)
    renewed = float(current.get("renewed") or current.get("since") or 0)
    if dead and current["id"] == dead:
        verdict = "take", f"took the lock left by {who}: that run has ended (its process is gone)"
    elif break_lock:
        verdict = "take", f"took the lock from {who} (isaac_sim_lock_break)"
    elif stale_after and now - renewed >= stale_after:
        verdict = (
            "take",
            f"took the lock from {who}: not renewed for {int(now - renewed)} s (isaac_sim_lock_stale_after)",
        )
    else:
        return "held", who
    # an ended run's lifecycle job may still be restarting an instance here (it stops before its next
    # one once its controller is silent): the host is taken over only once that job has ended, unless the
    # operator breaks the lock (the escape from a job that hangs)
    job = "" if break_lock else job_running(current)
    if job:
        return "job", (
            f"{who} has ended, but its lifecycle job still runs on this host ({job}); it stops before its next "
            f"instance within {HEARTBEAT_LIMIT_S} s of its controller's last renewal, once the instance in hand is "
            "ready or back"
        )
    return verdict


def start_time(pid: int) -> str:
    """A process's start time (/proc/PID/stat, field 22): with the pid, who it is (a pid is reused)."""
    try:
        with open(f"/proc/{int(pid)}/stat") as fh:
            return fh.read().rsplit(")", 1)[1].split()[19]
    except (OSError, ValueError, IndexError):
        return ""


def job_running(current) -> str:
    """'pid N' while the lifecycle job the holder `current` recorded (mark_job) still runs; "" otherwise."""
    job = (current or {}).get("job") if isinstance(current, dict) else None
    if not isinstance(job, dict) or not job.get("pid"):
        return ""
    started = start_time(job["pid"])
    if not started or (job.get("started") and started != job["started"]):
        return ""
    return f"pid {job['pid']}"


def mark_job(run_id: str, pid: int, path: str = LOCK, guard: str = "") -> bool:
    """The lifecycle job of run `run_id` records itself in the lock while it runs, so no other run
    takes the host over until it has ended (decide); only while that run holds the lock."""
    with _held_by({"id": run_id}, path, guard or guard_of(path)) as current:
        if current is None:
            return False
        current["job"] = {"pid": pid, "started": start_time(pid)}
        _write(path, current, 0o644)
        return True


def clear_job(run_id: str, pid: int, path: str = LOCK, guard: str = "") -> None:
    with _held_by({"id": run_id}, path, guard or guard_of(path)) as current:
        if current is not None and (current.get("job") or {}).get("pid") == pid:
            del current["job"]
            _write(path, current, 0o644)


def guard_of(path: str) -> str:
    return os.path.join(os.path.dirname(path), os.path.basename(GUARD))


def _write(path: str, data: dict, mode=None) -> None:
    """The whole file or none of it: readers never see half a holder."""
    # the process and thread: an agent's renewer and its lifecycle call write from one process
    tmp = f"{path}.{os.getpid()}.{threading.get_ident()}.tmp"
    with open(tmp, "w") as out:
        json.dump(data, out, sort_keys=True)
    if mode is not None:
        os.chmod(tmp, mode)
    os.replace(tmp, path)


def read(path: str = LOCK):
    """The lock's holder, None when free, {} when the file cannot be read as a holder."""
    try:
        with open(path) as fh:
            text = fh.read()
    except FileNotFoundError:
        return None
    try:
        data = json.loads(text)
    except ValueError:
        return {}
    return data if isinstance(data, dict) else {}


def acquire(
    me: dict, now: float, stale_after: int, break_lock=False, dead="", path=LOCK, guard=GUARD, record_path=RECORD
):
    """Take or renew the lock for `me`. Returns (acquired, holder, note); holder is the run that
    holds it after the call."""
    os.makedirs(os.path.dirname(path), mode=0o755, exist_ok=True)
    with open(guard, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        current = read(path)
        verdict, said = decide(current, me, now, stale_after, break_lock, dead)
        if verdict in ("held", "job"):
            return False, current, said
        if said and current:
            said += recorded_text(read(record_path), current["id"])
        keep = current if current and current.get("id") == me["id"] else {}
        holder = {k: me.get(k) for k in HOLDER_KEYS}
        holder.update(since=keep.get("since", now), renewed=now)
        if keep.get("job"):  # this run's own job, running: it stays recorded
            holder["job"] = keep["job"]
        _write(path, holder, 0o644)
        return True, holder, said


@contextlib.contextmanager
def _held_by(me: dict, path: str, guard: str):
    """The lock's record, under the guard, while `me` holds it; None when it does not (or no lock)."""
    if not os.path.exists(path):
        yield None
        return
    with open(guard, "a") as fh:
        fcntl.flock(fh, fcntl.LOCK_EX)
        current = read(path)
        yield current if current and current.get("id") == me["id"] else None


def renew(me: dict, now: float, path: str = LOCK, guard: str = GUARD) -> bool:
    """The controller's heartbeat: renews the lock when `me` holds it, never takes it."""
    with _held_by(me, path, guard) as current:
        if current is None:
            return False
        current["renewed"] = now
        _write(path, current, 0o644)
        return True


def gone(run_id: str, now: float, limit: float = HEARTBEAT_LIMIT_S, path: str = LOCK) -> str:
    """Why the run `run_id`, which held the lock, is taken for gone; "" while it renews it."""
    current = read(path)
    if not current:
        return "the host's lock was given back or removed"
    if current.get("id") != run_id:
        return f"the host's lock was taken by {holder_text(current, now)}"
    age = now - float(current.get("renewed") or 0)
    if age > limit:
        return f"its controller stopped renewing its hold on the host {int(age)} s ago (interrupted, or gone)"
    return ""


def record(entry: dict, path: str = RECORD) -> None:
    """Keep what a rollout step did (run, at, done, untouched, interrupted) for the next run."""
    os.makedirs(os.path.dirname(path), mode=0o755, exist_ok=True)
    _write(path, entry)


def recorded_text(entry, run_id: str) -> str:
    """What run `run_id` left on the host, from its record, for the note of the run that takes over."""
    if not isinstance(entry, dict) or entry.get("run") != run_id or not entry.get("interrupted"):
        return ""
    done = ", ".join(layout.container(i) for i in entry.get("done", [])) or "none"
    left = ", ".join(layout.container(i) for i in entry.get("untouched", [])) or "none"
    return f"; its rollout here was interrupted ({entry['interrupted']}): done {done}; left as they were {left}"


def release(me: dict, path: str = LOCK, guard: str = GUARD) -> bool:
    """Give the lock back when `me` holds it; a lock another run took over is left to it."""
    with _held_by(me, path, guard) as current:
        if current is None:
            return False
        os.unlink(path)
        return True


class LockError(Exception):
    """The lock module fails with this message."""


def request(p: dict, now: float, check=False, path: str = "", guard: str = "", record_path: str = "") -> dict:
    """The isaac_sim_lock module's result (changed aside) for its parameters `p`: the lock taken,
    renewed or given back for p["holder"]; in check mode only what would be. path, guard,
    record_path: the lock's files (LOCK, GUARD, RECORD when empty)."""
    path, guard, record_path = path or LOCK, guard or GUARD, record_path or RECORD
    me = p.get("holder") or {}
    if not me.get("id"):
        raise LockError(
            "holder: needs an id. Fix: call isaacsim.fleet.isaac_sim_lock as a task (its action plugin fills it)."
        )
    try:
        if p["state"] == "renewed":
            renewed = False if check else renew(me, now, path, guard)
            return {"acquired": renewed, "holder": None, "note": ""}
        if p["state"] == "absent":
            released = False if check else release(me, path, guard)
            return {"acquired": False, "released": released, "holder": None, "note": ""}
        if check:
            current = read(path)
            verdict, said = decide(current, me, now, p["stale_after"], p["break_lock"], p["dead"])
            return {"acquired": verdict == "take", "holder": current, "note": said, "job_running": verdict == "job"}
        acquired, holder, note = acquire(
            me, now, p["stale_after"], p["break_lock"], p["dead"], path, guard, record_path
        )
    except OSError as exc:
        raise LockError(f"the lock {path}: {exc}") from exc
    # not taken over while the ended holder's lifecycle job runs here: the controller waits for it
    job = not acquired and decide(holder, me, now, p["stale_after"], p["break_lock"], p["dead"])[0] == "job"
    return {"acquired": acquired, "holder": holder, "note": note, "job_running": job}
