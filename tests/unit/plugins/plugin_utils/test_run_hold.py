"""How a run is named to a host's lock and one that has ended is found (plugins/plugin_utils/run_hold.py,
for the lock's action plugin), against real processes."""

import os
import subprocess

from ansible_collections.isaacsim.fleet.plugins.plugin_utils import run_hold


def test_a_run_is_its_ansible_playbook_process_with_its_start_time():
    me = run_hold.this_run("Deploy")
    assert me["pid"] == os.getppid() and me["started"]
    assert me["id"] == f"{me['controller']}:{me['pid']}:{me['started']}" and me["play"] == "Deploy"


def test_a_live_run_is_alive_and_an_ended_or_reused_pid_is_not():
    child = subprocess.Popen(["sleep", "30"])
    started = run_hold._start_time(child.pid)
    try:
        assert run_hold.alive(child.pid, started)
        # the same pid, another process (a start time that is not its own)
        assert not run_hold.alive(child.pid, str(int(started) - 1))
    finally:
        child.kill()
        child.wait()
    assert not run_hold.alive(child.pid, started)


def test_an_ended_run_whose_job_still_runs_on_the_host_is_waited_for_then_taken_over(tmp_path, monkeypatch):
    """The real runlock on a lock file of the test's: a killed run of this controller (its process gone)
    left its lifecycle job running on the host; the next run waits for the job (told once), whatever
    isaac_sim_lock_wait says, and takes the host over once it has ended."""
    from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import runlock

    lock, guard = str(tmp_path / "isaac-sim.json"), str(tmp_path / ".isaac-sim.guard")
    gone = subprocess.Popen(["true"])
    gone.wait()  # the killed ansible-playbook: a pid of this controller that has ended
    me = run_hold.this_run("Deploy")
    ended = dict(me, id=f"{me['controller']}:{gone.pid}:1", pid=gone.pid, started="1")
    runlock.acquire(ended, 1000.0, 3600, path=lock, guard=guard, record_path="")
    job = subprocess.Popen(["sleep", "30"])
    runlock.mark_job(ended["id"], job.pid, path=lock, guard=guard)
    told, sleeps = [], []
    monkeypatch.setattr(run_hold.display, "display", told.append)
    monkeypatch.setattr(run_hold.display, "warning", told.append)

    def sleep(seconds):
        sleeps.append(seconds)
        if len(sleeps) == 3:  # the job stops before its next instance
            job.kill()
            job.wait()

    monkeypatch.setattr(run_hold.time, "sleep", sleep)
    request = {"holder": me, "state": "present", "stale_after": 3600, "break_lock": False, "dead": "", "wait": 0}

    def execute(asked):
        answer = runlock.request(asked, 1100.0, path=lock, guard=guard, record_path="")
        return answer, dict(answer, changed=answer["acquired"])

    try:
        result = run_hold.hold(execute, request, "gpu-1", check_mode=False)
    finally:
        job.kill()
        job.wait()
    assert result["acquired"] is True and runlock.read(lock)["id"] == me["id"]
    assert sleeps == [run_hold.POLL_S] * 3
    waiting = [t for t in told if "its lifecycle job still runs on this host" in t]
    assert len(waiting) == 1 and "waiting for it to end (at most 900 s)" in waiting[0]
    assert any("took the lock left by" in t for t in told)
