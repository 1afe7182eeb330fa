# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
"""A playbook run's hold on a host (controller side, for the action plugins): the run named as the host's
lock records it, the wait while another run holds the host, and holders found to have ended: a run of
this same controller whose ansible-playbook process is gone gives its lock up at once, whatever its age.
Used by the actions of isaac_sim_lock, isaac_sim_plan (which takes the lock in its own call),
isaac_sim_lifecycle and isaac_sim_results_lock."""

import getpass
import os
import socket
import time

from ansible.utils.display import Display
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import runlock

display = Display()
POLL_S = 5
# the longest an ended run's lifecycle job is waited for: it stops before its next instance within
# runlock.HEARTBEAT_LIMIT_S of its controller's silence, once the instance in hand is ready (its ready
# timeout, 300 s by default) and soaked, or back
JOB_WAIT_S = 900
_start_time = runlock.start_time


def alive(pid, started: str) -> bool:
    """Whether the process is still the one that started then (a pid reused since is not)."""
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except (PermissionError, TypeError, ValueError):
        return True
    return not started or _start_time(int(pid)) in ("", started)


def this_run(play: str) -> dict:
    """This playbook run, as a lock records its holder."""
    # action plugins run in a worker forked from ansible-playbook: the parent is the run itself
    pid = os.getppid()
    started = _start_time(pid)
    controller = socket.gethostname()
    return {
        "id": f"{controller}:{pid}:{started}",
        "user": getpass.getuser(),
        "controller": controller,
        "pid": pid,
        "started": started,
        "play": play,
    }


def hold(execute, lock: dict, host: str, check_mode: bool) -> dict:
    """The module's result once the lock is taken, renewed or given back (lock: the lock's options, holder
    filled), or the failure after `wait` seconds of another run holding it. execute(lock) -> (the lock's
    part of the module's result, the whole result): the lock module's, or the plan's, which takes the lock
    in its own call. A holder of this controller that has ended is taken over at once."""
    me, wait = lock["holder"], int(lock.get("wait") or 0)
    begun, told, job_begun = time.monotonic(), False, None
    while True:
        looked, whole = execute(lock)
        if whole.get("failed") or looked.get("acquired") or lock.get("state") in ("absent", "renewed"):
            if looked.get("note"):
                display.warning(f"{host}: {looked['note']}")
            return whole
        holder = looked.get("holder") or {}
        # the holder has ended but its lifecycle job on the host still finishes the instance in hand: waited
        # for whatever isaac_sim_lock_wait says (it ends by itself), so two lifecycles never run side by side
        if looked.get("job_running") and not check_mode:
            if job_begun is None:
                job_begun = time.monotonic()
                display.display(f"{host}: {looked.get('note')}; waiting for it to end (at most {JOB_WAIT_S} s)")
            if time.monotonic() - job_begun >= JOB_WAIT_S:
                return dict(
                    whole,
                    failed=True,
                    msg=(
                        f"{host}: {looked.get('note')}, and it did not end within {JOB_WAIT_S} s. Fix: see what it "
                        f"does (journalctl -t isaac-sim-lifecycle on {host}) and run again once it has ended."
                    ),
                )
            time.sleep(POLL_S)
            continue
        ended = not alive(holder.get("pid"), holder.get("started"))
        if holder.get("controller") == me["controller"] and ended and lock.get("dead") != holder.get("id"):
            lock = dict(lock, dead=holder.get("id", ""))
            continue
        who = runlock.holder_text(holder, time.time())
        if check_mode:
            display.warning(f"{host} is held by {who}; this dry run plans against a host that may be changing")
            return dict(whole, failed=False)
        if time.monotonic() - begun >= wait:
            return dict(
                whole,
                failed=True,
                msg=(
                    f"{host} is held by {who}: another run is changing its instances, and this one changes "
                    f"nothing while it does. Fix: wait for that run to end and run again, or set "
                    f"isaac_sim_lock_wait (seconds) to wait for it; if that run is dead (killed, or its "
                    f"controller gone), run again with -e isaac_sim_lock_break=true."
                ),
            )
        if not told:
            display.display(f"{host}: held by {who}; waiting up to {wait} s")
            told = True
        time.sleep(POLL_S)
