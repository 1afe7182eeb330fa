"""How the train job's action plugin follows a job, against the answers the module gives (state=query)
and a clock of its own: a job that stays COMPLETING past completing_timeout fails the follow with
the nodes it waits for; one that leaves COMPLETING in time is followed to its end."""

from __future__ import annotations

from unittest import mock

import pytest
from ansible_collections.isaacsim.fleet.plugins.action import isaac_sim_train_job

STUCK_NODE = {"node-2": {"state": "IDLE+COMPLETING+NOT_RESPONDING", "reason": ""}, "node-1": {"state": "IDLE"}}


def answer(state, **over):
    looked = {"id": "7", "state": state, "elapsed": "00:00:05", "nodes": "node-[1-2]", "finished": False}
    looked.update(over)
    return looked


@pytest.fixture
def follow(monkeypatch):
    """Runs the plugin with state=finished on a list of the module's answers (the last repeats);
    each poll moves the plugin's clock on by the poll interval."""
    clock = {"now": 1000.0}
    monkeypatch.setattr(isaac_sim_train_job.time, "monotonic", lambda: clock["now"])
    monkeypatch.setattr(isaac_sim_train_job.time, "sleep", lambda s: clock.__setitem__("now", clock["now"] + s))
    monkeypatch.setattr(isaac_sim_train_job.display, "display", lambda *a, **k: None)

    def run(answers, **args):
        task = mock.MagicMock(async_val=0, check_mode=False, delegate_to=None)
        task.args = dict({"state": "finished", "job_id": "7", "poll_interval": 10}, **args)
        connection = mock.MagicMock()
        connection._shell.tmpdir = "/tmp/x"
        plugin = isaac_sim_train_job.ActionModule(task, connection, mock.MagicMock(), None, None, None)
        given = list(answers)
        plugin._execute_module = lambda module_args, task_vars: given.pop(0) if len(given) > 1 else given[0]
        return plugin.run(task_vars={"inventory_hostname": "login"})

    return run


def test_a_job_that_stays_completing_fails_the_follow_naming_the_node_it_waits_for(follow):
    result = follow([answer("RUNNING"), answer("COMPLETING", node_states=STUCK_NODE)], completing_timeout=30)
    assert result["failed"] and result["stuck_nodes"] == ["node-2"] and result["stuck_for"] == 30
    assert result["msg"].startswith(
        "job 7 has been COMPLETING for 30 s (Slurm's reason: none): slurmctld waits for node-2 "
        "(IDLE+COMPLETING+NOT_RESPONDING) to end it"
    )
    assert "journalctl -u slurmd -u munge on node-2" in result["msg"]
    assert result["progress"] == ["job 7 RUNNING 00:00:05 node-[1-2]", "job 7 COMPLETING 00:00:05 node-[1-2]"]


def test_a_job_that_leaves_completing_within_the_bound_is_followed_to_its_end(follow):
    completing = [answer("COMPLETING")] * 5
    result = follow(
        completing + [answer("COMPLETED", finished=True, exit_code=0)], completing_timeout=60, wait_timeout=0
    )
    assert not result.get("failed") and result["state"] == "COMPLETED"
    # the bound counts a stretch of COMPLETING, from its start
    again = follow(
        [answer("COMPLETING")] * 3
        + [answer("RUNNING")]
        + [answer("COMPLETING")] * 3
        + [answer("FAILED", finished=True)],
        completing_timeout=35,
    )
    assert not again.get("failed") and again["state"] == "FAILED"


@pytest.mark.parametrize("bound", [0, -5, "abc"])
def test_the_bound_is_a_positive_number_of_seconds(follow, bound):
    result = follow([answer("RUNNING")], completing_timeout=bound)
    assert result["failed"] and result["msg"].startswith("completing_timeout: ")
    assert "1 or more (train_completing_timeout)" in result["msg"]
