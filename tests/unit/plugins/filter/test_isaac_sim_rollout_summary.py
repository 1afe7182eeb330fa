"""The isaac_sim_rollout_summary filter, as the rollout's callers write it (roles/isaac_sim/tasks/rollout.yml,
playbooks/rollout.yml, playbooks/deploy.yml), on the results isaac_sim_lifecycle gives: each host's
outcome is what one real lifecycle call on a scripted host returns (fail_json's fields on a failure),
or the lock's failure, or {} for a host not reached."""

from __future__ import annotations

import json
import os

from ansible_collections.isaacsim.fleet.plugins.filter.isaac_sim_rollout_summary import FilterModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import lifecycle_call, plan
from ansible_collections.isaacsim.fleet.tests.unit.helpers import plan_config
from ansible_collections.isaacsim.fleet.tests.unit.plugins.filter.conftest import find_task, load, trusted
from ansible_collections.isaacsim.fleet.tests.unit.plugins.module_utils.instance.test_lifecycle import (
    CRASHY,
    ScriptedHost,
)

ROLLOUT = "roles/isaac_sim/tasks/rollout.yml"
HOSTS = ["gpu-1", "gpu-2", "gpu-3"]
# {host: outcome} from the play's hosts (roles/isaac_sim/vars/main.yml)
OUTCOMES = trusted(load("roles/isaac_sim/vars/main.yml")["__isaac_sim_rollout_outcomes"])


def lifecycle_result(h: ScriptedHost, tmp_path, **args) -> dict:
    """What the play registers for one isaac_sim_lifecycle task: the module's result, or on a failure
    fail_json's (failed, msg and the result's fields)."""
    p = {
        "action": "restart",
        "ids": [],
        "plan": None,
        "image_id": "unknown",
        "secret_env": {},
        "scripts": {name: "#!/bin/sh\n" for name in (*layout.SCRIPTS, *layout.POLICY_LIB)},
        "managed": "managed",
        "soak_seconds": 10,
        "defer_running": False,
        "remove_others": True,
        "purge": False,
        "data_root": str(tmp_path / "data"),
        "controller_run": "",
    }
    p.update(args)
    try:
        out = lifecycle_call.call(h.host, p, lock=str(tmp_path / "lock.json"), record=str(tmp_path / "record.json"))
    except lifecycle_call.LifecycleError as exc:
        return dict(exc.fields, failed=True, msg=exc.msg)
    return dict(out, failed=False)


def crashy_second(tmp_path) -> dict:
    """A rolling restart of four instances where instance 1 crashes during its soak."""
    h = ScriptedHost(4)
    h.files[layout.env_file(1)] = (CRASHY, 0o644)
    return lifecycle_result(h, tmp_path, ids=[0, 1, 2, 3])


def play(outcomes: dict) -> dict:
    """The play's variables with {host: its isaac_sim_rollout_outcome, or None when it has none}."""
    return {
        "ansible_play_hosts_all": HOSTS,
        "hostvars": {h: {} if o is None else {"isaac_sim_rollout_outcome": o} for h, o in outcomes.items()},
    }


def rescue_summary(render, outcomes: dict, failed_host: str) -> list:
    """The rescue's summary in rollout.yml, on `failed_host`, with {host: isaac_sim_rollout_outcome}."""
    task = find_task(
        ROLLOUT, "Summarize the rollout as it stopped", within="Roll the instances of this host one at a time"
    )
    variables = dict(play(outcomes), __isaac_sim_rollout_outcomes=OUTCOMES, inventory_hostname=failed_host)
    return render(task["ansible.builtin.debug"]["msg"], variables)


def test_a_rolling_restart_that_completes_names_every_instance_rolled(render, tmp_path):
    rolled = lifecycle_result(ScriptedHost(4), tmp_path, ids=[0, 1, 2, 3])
    nothing = lifecycle_result(ScriptedHost(2), tmp_path, ids=[])
    some = lifecycle_result(ScriptedHost(2), tmp_path, ids=[1])
    task = find_task("playbooks/rollout.yml", "Show what was rolled")
    variables = play({"gpu-1": rolled, "gpu-2": nothing, "gpu-3": some})
    assert render(task["ansible.builtin.debug"]["msg"], variables) == [
        "rolled: gpu-1: isaac-sim-0, isaac-sim-1, isaac-sim-2, isaac-sim-3; gpu-3: isaac-sim-1",
        "already current: gpu-2",
        "reverted: none",
        "untouched: none",
        "completed: every host rolled",
    ]


def test_a_crash_in_the_soak_stops_the_rollout_naming_the_instance_its_reason_and_where_it_is(render, tmp_path):
    first = lifecycle_result(ScriptedHost(4), tmp_path, ids=[0, 1, 2, 3])
    failed = crashy_second(tmp_path)
    assert failed["failed"] and failed["failed_instance"]["reverted"] is True
    reason = failed["failed_instance"]["reason"]
    assert "restarted during the soak" in reason
    lines = rescue_summary(render, {"gpu-1": first, "gpu-2": failed, "gpu-3": None}, "gpu-2")
    assert lines == [
        "rolled: gpu-1: isaac-sim-0, isaac-sim-1, isaac-sim-2, isaac-sim-3; gpu-2: isaac-sim-0",
        f"reverted: gpu-2: isaac-sim-1 ({reason}) - back on reg/isaac-sim:crashy, ready",
        "untouched: gpu-2: isaac-sim-2, isaac-sim-3; gpu-3: every instance (not reached)",
        f"stopped: isaac-sim-1 on gpu-2: {reason}",
    ]


def test_a_revert_that_fails_too_says_so():
    out = {
        "failed": True,
        "done": [],
        "failed_instance": {"id": 2, "reason": "not ready", "reverted": False, "revert_error": "no space left"},
        "untouched": [3],
    }
    lines = FilterModule().filters()["isaac_sim_rollout_summary"]({"gpu-1": out}, ["gpu-1"])
    assert lines == [
        "rolled: none",
        "reverted: gpu-1: isaac-sim-2 (not ready) - REVERT FAILED: no space left",
        "untouched: gpu-1: isaac-sim-3",
        "stopped: isaac-sim-2 on gpu-1: not ready",
    ]


def test_a_new_instance_that_never_gets_ready_is_left_stopped(tmp_path):
    h = ScriptedHost(1, running=False)
    built = plan.build(
        plan_config(instance_count=1, data_root=str(tmp_path / "data"), image="reg/isaac-sim:never-ready"), {}
    )
    built.update(uid=os.getuid(), gid=os.getgid())
    out = lifecycle_result(h, tmp_path, action="apply", plan=built)
    assert out["failed"] and out["failed_instance"]["reverted"] is None
    reason = out["failed_instance"]["reason"]
    assert reason.startswith("isaac-sim-0 was not ready within 20 s")
    assert FilterModule().filters()["isaac_sim_rollout_summary"]({"gpu-1": out}, ["gpu-1"], "gpu-1") == [
        "rolled: none",
        f"reverted: gpu-1: isaac-sim-0 ({reason}) - not started, stopped",
        "untouched: none",
        f"stopped: isaac-sim-0 on gpu-1: {reason}",
    ]


def test_every_new_instance_that_never_gets_ready_is_named_left_stopped(tmp_path):
    h = ScriptedHost(2, running=False)
    built = plan.build(
        plan_config(instance_count=2, data_root=str(tmp_path / "data"), image="reg/isaac-sim:never-ready"), {}
    )
    built.update(uid=os.getuid(), gid=os.getgid())
    out = lifecycle_result(h, tmp_path, action="apply", plan=built)
    assert out["failed"] and [f["id"] for f in out["failed_instances"]] == [0, 1]
    first, second = (f["reason"] for f in out["failed_instances"])
    assert FilterModule().filters()["isaac_sim_rollout_summary"]({"gpu-1": out}, ["gpu-1"], "gpu-1") == [
        "rolled: none",
        f"reverted: gpu-1: isaac-sim-0 ({first}) - not started, stopped; "
        f"gpu-1: isaac-sim-1 ({second}) - not started, stopped",
        "untouched: none",
        f"stopped: isaac-sim-0 on gpu-1: {first}; isaac-sim-1 on gpu-1: {second}",
    ]


def test_a_host_that_fails_before_its_instances_stops_the_rollout_with_its_message(render, tmp_path):
    first = lifecycle_result(ScriptedHost(2), tmp_path, ids=[0, 1])
    # the rescue's ansible_failed_result when the lock task of the batch failed (lock.yml)
    held = {
        "failed": True,
        "acquired": False,
        "msg": "gpu-2 is held by bob on ctl-2 (ansible-playbook pid 77) since 2026-11-22 13:00:00 UTC (5 min ago): "
        "another run is changing its instances, and this one changes nothing while it does.",
    }
    lines = rescue_summary(render, {"gpu-1": first, "gpu-2": held, "gpu-3": None}, "gpu-2")
    assert lines == [
        "rolled: gpu-1: isaac-sim-0, isaac-sim-1",
        "reverted: none",
        "untouched: gpu-3: every instance (not reached)",
        f"stopped: gpu-2: {held['msg']}",
    ]


def test_no_approval_after_the_canary_is_why_it_stopped(render, tmp_path):
    canary = lifecycle_result(ScriptedHost(2), tmp_path, ids=[0, 1])
    summary = find_task(ROLLOUT, "Summarize the rollout as it stopped", within="Stop after the canary without approval")
    variables = dict(play({"gpu-1": canary, "gpu-2": None, "gpu-3": None}), __isaac_sim_rollout_outcomes=OUTCOMES)
    assert render(summary["ansible.builtin.debug"]["msg"], variables) == [
        "rolled: gpu-1: isaac-sim-0, isaac-sim-1",
        "reverted: none",
        "untouched: gpu-2: every instance (not reached); gpu-3: every instance (not reached)",
        "stopped: no approval after the canary",
    ]


def test_the_deploy_names_new_instances_started_and_serving_ones_rolled(render, tmp_path):
    def deploy(h, **over):
        built = plan.build(plan_config(data_root=str(tmp_path / "data"), image="reg/isaac-sim:6.0.1", **over), {})
        built.update(uid=os.getuid(), gid=os.getgid())
        return lifecycle_result(h, tmp_path, action="apply", plan=built)

    fresh = deploy(ScriptedHost(4, running=False))
    assert [d["action"] for d in fresh["done"]] == ["start"] * 4
    # a serving host: the deploy's first play defers it (outcome {}), its canary batch rolls it
    rolled = deploy(ScriptedHost(2), instance_count=2)
    assert [d["action"] for d in rolled["done"]] == ["apply", "apply"]
    # deployed before with these settings: nothing to do
    h = ScriptedHost(2)
    deploy(h, instance_count=2)
    current = deploy(h, instance_count=2)
    assert current["done"] == [] and not current["changed"]
    task = find_task("playbooks/deploy.yml", "Summarize the instances changed")
    variables = dict(play({"gpu-1": fresh, "gpu-2": rolled, "gpu-3": current}), **trusted(task["vars"]))
    assert render(task["ansible.builtin.debug"]["msg"], variables) == [
        "rolled: gpu-1: isaac-sim-0, isaac-sim-1, isaac-sim-2, isaac-sim-3; gpu-2: isaac-sim-0, isaac-sim-1",
        "already current: gpu-3",
        "reverted: none",
        "untouched: none",
        "completed: every host rolled",
    ]


def test_a_rollout_interrupted_on_a_host_says_why_and_is_not_complete(render, tmp_path):
    first = lifecycle_result(ScriptedHost(4), tmp_path, ids=[0, 1, 2, 3])
    # this run holds gpu-2's lock and stops renewing it: the lifecycle stops before the next instance
    h = ScriptedHost(4)
    run = "ctl-1:4242:1795000000"
    (tmp_path / "lock.json").write_text(json.dumps({"id": run, "since": h.host.wall(), "renewed": h.host.wall()}))
    cut = lifecycle_result(h, tmp_path, ids=[0, 1, 2, 3], soak_seconds=30, controller_run=run)
    assert cut["failed"] and cut["failed_instance"] is None and [d["id"] for d in cut["done"]] == [0]
    assert cut["interrupted"].startswith("its controller stopped renewing its hold on the host")
    assert cut["msg"] == (
        f"rollout interrupted: {cut['interrupted']}; it stopped before isaac-sim-1, isaac-sim-2, isaac-sim-3, "
        "which are as they were"
    )
    outcomes = {"gpu-1": first, "gpu-2": cut, "gpu-3": None}
    expected = [
        "rolled: gpu-1: isaac-sim-0, isaac-sim-1, isaac-sim-2, isaac-sim-3; gpu-2: isaac-sim-0",
        "reverted: none",
        "untouched: gpu-2: isaac-sim-1, isaac-sim-2, isaac-sim-3; gpu-3: every instance (not reached)",
        f"stopped: gpu-2: {cut['msg']}",
    ]
    assert rescue_summary(render, outcomes, "gpu-2") == expected
    # the summary at the end of playbooks/rollout.yml (a rollout that goes on past a failed host)
    task = find_task("playbooks/rollout.yml", "Show what was rolled")
    assert render(task["ansible.builtin.debug"]["msg"], play(outcomes)) == expected
