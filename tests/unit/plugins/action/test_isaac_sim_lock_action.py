"""How the lock's action plugin names a run and finds one that has ended, against real processes."""

import os
import subprocess

from ansible_collections.isaacsim.fleet.plugins.action import isaac_sim_lock


def test_a_run_is_its_ansible_playbook_process_with_its_start_time():
    me = isaac_sim_lock.this_run("Deploy")
    assert me["pid"] == os.getppid() and me["started"]
    assert me["id"] == f"{me['controller']}:{me['pid']}:{me['started']}" and me["play"] == "Deploy"


def test_a_live_run_is_alive_and_an_ended_or_reused_pid_is_not():
    child = subprocess.Popen(["sleep", "30"])
    started = isaac_sim_lock._start_time(child.pid)
    try:
        assert isaac_sim_lock._alive(child.pid, started)
        # the same pid, another process (a start time that is not its own)
        assert not isaac_sim_lock._alive(child.pid, str(int(started) - 1))
    finally:
        child.kill()
        child.wait()
    assert not isaac_sim_lock._alive(child.pid, started)
