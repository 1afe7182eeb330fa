"""The plan's action plugin with lock (playbooks/deploy.yml's one call for the lock and the plan): it names
this run, waits while another run holds the host and takes over a holder of this controller that has
ended, as the lock's own action does. The host's side is a stand-in of the module whose lock is real
(runlock, on a lock file of the test's)."""

from __future__ import annotations

from types import SimpleNamespace
from unittest import mock

import pytest
from ansible_collections.isaacsim.fleet.plugins.action import isaac_sim_plan as plugin
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import host_facts, runlock
from ansible_collections.isaacsim.fleet.plugins.plugin_utils import run_hold

PLAY = "Validate"
PLAN = {"ids": [0, 1], "image": "nvcr.io/nvidia/isaac-sim:6.0.1"}
BOB = {"id": "ctl-2:200:7", "user": "bob", "controller": "ctl-2", "pid": 200, "started": "7", "play": "Deploy"}


class Host:
    """The module on the host: the lock taken as the module takes it, then the plan; a clock of its own."""

    def __init__(self, tmp_path, released_at=None):
        self.now = 1000.0
        self.files = {"path": str(tmp_path / "isaac-sim.json"), "guard": str(tmp_path / ".guard"), "record_path": ""}
        self.released_at, self.calls = released_at, []

    def hold(self, holder):
        runlock.acquire(holder, self.now, 3600, **self.files)

    def execute(self, check_mode):
        def answer(module_name=None, module_args=None, task_vars=None):
            self.calls.append(dict(module_args))
            if not module_args.get("lock"):
                return {"changed": False, "plan": PLAN}
            if self.released_at is not None and self.now >= self.released_at:
                runlock.release(BOB, self.files["path"], self.files["guard"])
            # the module's own call (its argument spec's defaults filled in), the plan itself a stand-in
            lock = dict({"stale_after": 3600, "break_lock": False, "dead": "", "wait": 0}, **module_args["lock"])
            probe = SimpleNamespace(check_mode=check_mode, min_facts=dict)
            return dict(host_facts.plan_held(probe, dict(module_args, lock=lock), self.now), changed=False)

        return answer


@pytest.fixture
def run(monkeypatch):
    def go(host, args, check_mode=False):
        monkeypatch.setattr(runlock, "LOCK", host.files["path"])
        monkeypatch.setattr(runlock, "GUARD", host.files["guard"])
        monkeypatch.setattr(runlock, "RECORD", "")
        planned = {"plan": PLAN, "stale_ids": [], "host": {}, "warnings": []}
        monkeypatch.setattr(host_facts, "plan_host", lambda probe, p: dict(planned))
        clock = mock.MagicMock()
        clock.monotonic = lambda: host.now
        clock.time = lambda: host.now
        clock.sleep = lambda s: setattr(host, "now", host.now + s)
        monkeypatch.setattr(run_hold, "time", clock)
        task = mock.MagicMock(check_mode=check_mode, async_val=0)
        task.args = dict(args)
        action = plugin.ActionModule(task, mock.MagicMock(), mock.MagicMock(), None, None, None)
        action._execute_module = host.execute(check_mode)
        return action.run(task_vars={"ansible_play_name": PLAY, "inventory_hostname": "gpu-1"})

    return go


def test_without_lock_the_plan_is_one_call_with_its_arguments_as_given(run, tmp_path):
    host = Host(tmp_path)
    result = run(host, {"release": "6.x"})
    assert host.calls == [{"release": "6.x"}] and result["plan"] == PLAN


def test_a_free_host_is_held_by_this_run_and_planned_in_one_call(run, tmp_path):
    host = Host(tmp_path)
    result = run(host, {"release": "6.x", "lock": {"wait": 0}})
    [call] = host.calls
    assert call["lock"]["holder"] == run_hold.this_run(PLAY) and call["release"] == "6.x"
    assert result["lock"]["acquired"] and result["plan"] == PLAN and not result.get("failed")
    assert runlock.read(host.files["path"])["id"] == run_hold.this_run(PLAY)["id"]


def test_a_host_another_run_holds_is_waited_for_then_refused_naming_the_holder(run, tmp_path):
    host = Host(tmp_path)
    host.hold(BOB)
    result = run(host, {"release": "6.x", "lock": {"wait": 12}})
    assert result["failed"] and "plan" not in result
    assert result["msg"].startswith("gpu-1 is held by bob on ctl-2") and "isaac_sim_lock_wait" in result["msg"]
    # asked at 0, 5, 10 and 15 s: every POLL_S until the wait is over
    assert len(host.calls) == 4 and host.now == 1015.0


def test_a_host_released_while_waiting_is_taken_and_planned(run, tmp_path):
    host = Host(tmp_path, released_at=1007.0)
    host.hold(BOB)
    result = run(host, {"release": "6.x", "lock": {"wait": 60}})
    assert result["lock"]["acquired"] and result["plan"] == PLAN and not result.get("failed")
    assert len(host.calls) == 3


def test_the_lock_of_an_ended_run_of_this_controller_is_taken_at_once(run, tmp_path):
    host = Host(tmp_path)
    me = run_hold.this_run(PLAY)
    # this controller, a pid that runs no process (pid_max is at most 2**22)
    ended = dict(me, id=f"{me['controller']}:4194304:1", pid=4194304, started="1", user="carol")
    host.hold(ended)
    result = run(host, {"release": "6.x", "lock": {"wait": 0}})
    assert [c["lock"].get("dead", "") for c in host.calls] == ["", ended["id"]]
    assert result["lock"]["acquired"] and result["plan"] == PLAN
    assert "took the lock left by carol" in result["lock"]["note"]


def test_a_dry_run_plans_against_a_held_host_and_does_not_fail(run, tmp_path):
    host = Host(tmp_path)
    host.hold(BOB)
    result = run(host, {"release": "6.x", "lock": {"wait": 60}}, check_mode=True)
    assert result["plan"] == PLAN and not result["failed"] and len(host.calls) == 1
    assert runlock.read(host.files["path"])["id"] == BOB["id"]


def test_an_empty_lock_is_a_lock_with_its_defaults_and_this_run_named(run, tmp_path):
    host = Host(tmp_path)
    result = run(host, {"release": "6.x", "lock": {}})
    assert host.calls[0]["lock"]["holder"] == run_hold.this_run(PLAY) and result["lock"]["acquired"]
