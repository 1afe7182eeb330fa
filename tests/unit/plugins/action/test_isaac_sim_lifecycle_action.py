"""The lifecycle's action plugin, around the module it runs on the host: the module goes to the background
as an async job while the plugin renews this run's hold on the host (the lock) and asks for the job,
with a clock of its own. The host's side of the calls is a stand-in: the lock's renewals are real
(runlock, on a lock file of the test's), and the job counts as interrupted, as the module would
find it, whenever runlock says the controller has been silent past HEARTBEAT_LIMIT_S."""

from __future__ import annotations

from unittest import mock

import pytest
from ansible.module_utils.common.arg_spec import ArgumentSpecValidator
from ansible_collections.isaacsim.fleet.plugins.action import isaac_sim_lifecycle as plugin
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import runlock
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_lifecycle as lifecycle_module
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_lock as lock_module
from ansible_collections.isaacsim.fleet.plugins.plugin_utils.run_hold import this_run

PLAY = "Roll this batch"
# rollout.yml's rolling restart, as its task's arguments render
RESTART = {"action": "restart", "ids": [0, 1, 2, 3], "soak_seconds": 30}
DONE = {
    "changed": True,
    "done": [{"id": i, "action": "restart", "restart_s": 6.0, "soak_s": 30.0} for i in range(4)],
    "failed_instance": None,
    "untouched": [],
}
ASYNC_DIR = "/home/ops/.ansible_async"


class Host:
    """The host's side of _execute_module: the lifecycle job, the lock module and async_status."""

    def __init__(self, tmp_path, job_s=120.0, outcome=None, start=None, status=None, look=None, poll_s=0.0):
        """job_s: how long the job runs; outcome: the module's result; start: the answer to starting
        the job instead of a job id; status: async_status's answer instead of the job's; look: the
        module's answer in check mode (an apply's first look), the outcome when None; poll_s: how long
        each ask for the job takes (a loaded host or connection)."""
        self.now = 1000.0
        self.poll_s = poll_s
        self.lock = str(tmp_path / "isaac-sim.json")
        self.guard = str(tmp_path / ".isaac-sim.guard")
        self.job_s, self.start, self.status, self.look = job_s, start, status, look
        self.outcome = dict(DONE if outcome is None else outcome)
        self.calls, self.job, self.interrupted, self.check_modes = [], None, "", []
        # this run holds the host, as lock.yml left it
        runlock.acquire(this_run(PLAY), self.now, 3600, path=self.lock, guard=self.guard, record_path="")

    def sleep(self, seconds):
        self.now += seconds
        # a plugin that would wait on forever fails the test instead
        assert self.now < 1000.0 + self.job_s + 600, "still waiting long after the job ended"

    def execute(self, task):
        def answer(module_name=None, module_args=None, task_vars=None, wrap_async=False):
            self.calls.append((module_name, dict(module_args), wrap_async, task.async_val))
            self.check_modes.append(task.check_mode)
            if module_name is None:
                if not wrap_async:  # the module itself, in the task
                    return dict(self.outcome if self.look is None or not task.check_mode else self.look)
                if self.start is not None:
                    return dict(self.start)
                self.job = {"jid": "j4711", "run": module_args.get("controller_run"), "ends": self.now + self.job_s}
                return {"ansible_job_id": "j4711", "started": 1, "finished": 0, "results_file": "/x/j4711"}
            if module_name == "isaacsim.fleet.isaac_sim_lock":
                # what the job would see now, the longest the controller has been silent
                self.interrupted = self.interrupted or runlock.gone(self.job["run"], self.now, path=self.lock)
                return dict(runlock.request(module_args, self.now, path=self.lock, guard=self.guard), changed=False)
            assert module_name == "ansible.legacy.async_status"
            self.now += self.poll_s
            if self.status is not None:
                return dict(self.status)
            if module_args.get("mode") == "cleanup":
                return {"ansible_job_id": module_args["jid"], "erased": "/x/j4711"}
            job = {"ansible_job_id": "j4711", "started": 1, "results_file": "/x/j4711"}
            if self.now < self.job["ends"]:
                return dict(job, finished=0)
            out = dict(self.outcome, stdout_lines=[], stderr_lines=[])
            if self.interrupted:
                out.update(failed=True, msg=f"rollout interrupted: {self.interrupted}")
            return dict(job, finished=1, **out)

        return answer

    def called(self, module_name):
        return [c for c in self.calls if c[0] == module_name]


@pytest.fixture
def run(monkeypatch):
    """run(host, args, check_mode, async_val) -> (result, task, the tmp paths removed, the sleeps)."""

    def go(host, args, check_mode=False, async_val=0):
        sleeps = []
        monkeypatch.setattr(plugin.time, "sleep", lambda s: (sleeps.append(s), host.sleep(s)))
        # the plugin's clock is the host's: the waits and the calls' own time
        monkeypatch.setattr(plugin.time, "monotonic", lambda: host.now)
        task = mock.MagicMock(async_val=async_val, check_mode=check_mode)
        task.args = dict(args)
        connection = mock.MagicMock(has_native_async=False)
        connection._shell.tmpdir = "/tmp/x"
        action = plugin.ActionModule(task, connection, mock.MagicMock(), None, None, None)
        removed = []
        action._execute_module = host.execute(task)
        action.get_shell_option = lambda option, default=None: default
        action._remote_expand_user = lambda path: path.replace("~", "/home/ops", 1)
        action._remove_tmp_path = removed.append
        result = action.run(task_vars={"ansible_play_name": PLAY, "inventory_hostname": "gpu-1"})
        return result, task, removed, sleeps

    return go


def valid(spec: dict, args: dict) -> dict:
    checked = ArgumentSpecValidator(spec).validate(args)
    assert checked.error_messages == []
    return checked.validated_parameters


def test_the_module_runs_as_a_job_while_the_lock_is_renewed_every_few_seconds(run, tmp_path):
    host = Host(tmp_path, job_s=120)
    result, task, removed, sleeps = run(host, RESTART)
    me = this_run(PLAY)
    # the job: the task's arguments and this run, under a day's async limit; the task is left as it was
    [(_name, args, wrapped, limit)] = host.called(None)
    assert wrapped and limit == plugin.JOB_LIMIT_S == 86400
    assert args == dict(RESTART, controller_run=me["id"])
    assert valid(lifecycle_module.ARGUMENT_SPEC, args)["controller_run"] == me["id"]
    assert task.async_val == 0 and task.args == RESTART
    # the polls: soon at first, then every 5 s until the job ends; each asks for the job, and the
    # lock is renewed before the ask once 5 s of waiting have passed since the last renewal
    assert sleeps[:10] == [0.25, 0.25, 0.5, 1, 1, 2, 2, 3, 5, 5] and set(sleeps[8:]) == {5} and sum(sleeps) >= 120
    expected, waited = [], 0.0
    for wait in sleeps:
        waited += wait
        if waited >= plugin.RENEW_S:
            expected.append("isaacsim.fleet.isaac_sim_lock")
            waited = 0.0
        expected.append("ansible.legacy.async_status")
    names = [c[0] for c in host.calls[1:]]
    assert names == expected + ["ansible.legacy.async_status"]
    # the first renewal after 0.25 + 0.25 + 0.5 + 1 + 1 + 2 = 5 s, then every 5 s
    assert names[:7] == ["ansible.legacy.async_status"] * 5 + ["isaacsim.fleet.isaac_sim_lock"] * 1 + [
        "ansible.legacy.async_status"
    ]
    renewals = host.called("isaacsim.fleet.isaac_sim_lock")
    assert len(renewals) >= 120 // plugin.RENEW_S - 1
    assert all(c[1] == {"holder": me, "state": "renewed"} for c in renewals)
    valid(lock_module.ARGUMENT_SPEC, renewals[0][1])
    # so the host never took the controller for gone
    assert host.interrupted == "" and host.now - runlock.read(host.lock)["renewed"] < plugin.RENEW_S + plugin.POLL_MAX_S
    statuses = host.called("ansible.legacy.async_status")
    assert statuses[0][1] == {"jid": "j4711", "_async_dir": ASYNC_DIR}
    assert statuses[-1][1] == {"jid": "j4711", "mode": "cleanup", "_async_dir": ASYNC_DIR}
    # the module's result, without the job's bookkeeping
    assert result == DONE and removed == ["/tmp/x"]


def test_polls_that_take_seconds_of_their_own_still_renew_the_lock_by_the_clock(run, tmp_path):
    # each ask for the job takes 8 s (a loaded host): counting only its own waits, the plugin renewed
    # every six polls and the host took a live rollout for gone ("stopped renewing ... 33 s ago")
    host = Host(tmp_path, job_s=300, poll_s=8.0)
    result, _task, _removed, _sleeps = run(host, RESTART)
    assert host.interrupted == "" and result == DONE
    names = [c[0] for c in host.calls[1:-1]]
    # a renewal before every ask once the first 5 s have passed
    assert all(a != b for a, b in zip(names[3:], names[4:])), names


def test_a_controller_silent_past_the_heartbeat_limit_is_what_interrupts_the_job(run, tmp_path, monkeypatch):
    # the same job, polled every 31 s after the first few: the host takes the controller for gone
    monkeypatch.setattr(plugin, "POLL_MAX_S", runlock.HEARTBEAT_LIMIT_S + 1)
    host = Host(tmp_path, job_s=120)
    result, _task, _removed, _sleeps = run(host, RESTART)
    assert host.interrupted.startswith("its controller stopped renewing its hold on the host 31 s ago")
    assert result["failed"] and result["msg"] == f"rollout interrupted: {host.interrupted}"


def test_a_failed_instance_fails_the_task_with_the_module_s_message_and_fields(run, tmp_path):
    failed = {
        "changed": True,
        "failed": True,
        "msg": "isaac-sim-1: restarted during the soak (NRestarts 0 -> 1) after 4 s; it went back to "
        "reg/isaac-sim:5.0.0; not reached: isaac-sim-2, isaac-sim-3",
        "done": [{"id": 0, "action": "restart", "restart_s": 5.0, "soak_s": 30.0}],
        "failed_instance": {"id": 1, "reason": "restarted during the soak", "reverted": True},
        "untouched": [2, 3],
    }
    result, _task, removed, _sleeps = run(Host(tmp_path, job_s=40, outcome=failed), RESTART)
    assert result == failed and removed == ["/tmp/x"]


def test_a_job_that_does_not_start_is_the_task_s_failure_with_no_polls(run, tmp_path):
    refused = {"failed": True, "msg": "could not start the async wrapper", "rc": 127}
    host = Host(tmp_path, start=refused)
    result, _task, _removed, sleeps = run(host, RESTART)
    assert result == refused and sleeps == [] and len(host.calls) == 1


@pytest.mark.parametrize(
    "status",
    [
        # async_status's answer when the job's file is gone (a reboot, an async dir cleaned)
        {"failed": True, "msg": "could not find job", "ansible_job_id": "j4711", "started": True, "finished": True},
        # async_status itself could not run
        {"failed": True, "msg": "Module result deserialization failed: No start of json char found", "rc": 127},
    ],
)
def test_a_job_that_cannot_be_asked_for_ends_the_wait_with_the_answer(run, tmp_path, status):
    result, _task, removed, sleeps = run(Host(tmp_path, job_s=3600, status=status), RESTART)
    assert sleeps == [plugin.POLL_S[0]] and removed == ["/tmp/x"]
    assert result == {k: v for k, v in status.items() if k not in ("ansible_job_id", "started", "finished")}


def test_check_mode_runs_the_module_in_the_task_without_a_job(run, tmp_path):
    host = Host(tmp_path)
    result, task, _removed, sleeps = run(host, RESTART, check_mode=True)
    assert host.calls == [(None, dict(RESTART, controller_run=this_run(PLAY)["id"]), False, 0)]
    assert result == DONE and sleeps == [] and task.args == RESTART


def test_a_task_s_own_async_is_left_to_ansible(run, tmp_path):
    host = Host(tmp_path)
    result, task, removed, sleeps = run(host, RESTART, async_val=3600)
    # Ansible polls the job itself (or leaves it running, poll: 0), by the job id it gets back; no
    # heartbeat comes while it does, so the job is not tied to this run's hold on the host
    assert host.calls == [(None, RESTART, True, 3600)]
    assert result["ansible_job_id"] == "j4711" and result["started"] == 1
    assert sleeps == [] and removed == [] and task.args == RESTART and task.async_val == 3600


APPLY = {"action": "apply", "plan": {"release": "6.x", "instances": []}, "defer_running": True}
NOTHING = {"changed": False, "done": [], "failed_instance": None, "untouched": [], "plan": {"files": [], "start": []}}


def test_an_apply_with_nothing_to_change_is_answered_by_its_look_without_a_job(run, tmp_path):
    # an idempotent deploy's re-run: one call in check mode, and its answer is the task's
    host = Host(tmp_path, look=NOTHING)
    result, task, removed, sleeps = run(host, APPLY)
    assert host.calls == [(None, dict(APPLY, controller_run=this_run(PLAY)["id"]), False, 0)]
    assert host.check_modes == [True] and task.check_mode is False
    assert result == NOTHING and sleeps == [] and removed == []


def test_an_apply_that_would_change_runs_as_a_job_after_its_look(run, tmp_path):
    host = Host(tmp_path, job_s=3, look=dict(NOTHING, changed=True))
    result, task, _removed, _sleeps = run(host, APPLY)
    me = this_run(PLAY)["id"]
    assert host.calls[0] == (None, dict(APPLY, controller_run=me), False, 0)
    assert host.calls[1] == (None, dict(APPLY, controller_run=me), True, plugin.JOB_LIMIT_S)
    # the look in check mode, the job for real
    assert host.check_modes[:2] == [True, False] and task.check_mode is False
    assert result == DONE


def test_an_apply_whose_look_fails_fails_with_it_and_starts_no_job(run, tmp_path):
    # the real call would fail the same way before any change (a network changed since the plan)
    refused = {"failed": True, "msg": "the network isaac-sim-lan differs from the plan's and is in use"}
    host = Host(tmp_path, look=refused)
    result, _task, _removed, sleeps = run(host, APPLY)
    assert result == refused and len(host.calls) == 1 and sleeps == []
