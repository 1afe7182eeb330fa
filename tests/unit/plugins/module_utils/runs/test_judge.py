"""The verdict rules, one test each, on observations as the runner makes them."""

import yaml
from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import experience, judge
from ansible_collections.isaacsim.fleet.plugins.module_utils.runs.judge import EXITED, RESTARTING, RUNNING, STARTING


def read(text, **kw):
    exp, errors, _warnings = experience.read(yaml.safe_load(text), **kw)
    assert errors == []
    return exp


ROBOT = read(
    """
services:
  sim: {image: isaac-sim}
  db:
    image: reg/db:1
    healthcheck: {test: ["CMD", "true"]}
  planner:
    image: reg/planner:1
    depends_on: {db: {condition: service_healthy}, sim: {condition: service_healthy}}
  recorder:
    image: reg/recorder:1
    restart: on-failure
  check:
    image: reg/check:1
    labels: {isaacsim.fleet/test-orchestrator: "true"}
    depends_on: [planner]
"""
)


def obs(state=RUNNING, code=None, restarts=0, health=None):
    return judge.observation(state, code, restarts, health, state != "waiting")


def everything_running(**over):
    seen = {
        "sim": obs(),
        "db": obs(health="healthy"),
        "planner": obs(),
        "recorder": obs(),
        "check": obs(),
    }
    seen.update(over)
    return seen


def started_all(exp=ROBOT, timeout=60):
    """A judge that has started every service (each step starts what may start)."""
    j = judge.Judge(exp, timeout, 0.0)
    assert sorted(j.step(0.0, {"sim": obs()})) == ["db", "recorder"]
    assert j.step(1.0, {"sim": obs(), "db": obs(health="starting")}) == []  # planner waits for db's health
    assert j.step(2.0, everything_running(planner=judge.observation(), check=judge.observation())) == ["planner"]
    assert j.step(3.0, everything_running(check=judge.observation())) == ["check"]
    return j


def test_services_start_once_their_conditions_hold_in_compose_order():
    j = started_all()
    assert [e[1] for e in j.events if e[2].startswith("started")] == ["db", "recorder", "planner", "check"]
    # a dependency getting healthy is an event of its own, once: what its dependents waited for
    assert [e[:2] for e in j.events if e[2] == "healthy"] == [(2.0, "db")]
    assert j.verdict is None


def test_completed_successfully_waits_for_a_zero_exit_and_started_takes_a_service_that_already_finished():
    exp = read(
        """
services:
  seed: {image: reg/seed:1}
  migrate: {image: reg/migrate:1}
  test:
    image: reg/test:1
    labels: {resim.ai/isTestOrchestrator: "true"}
    depends_on: {seed: {condition: service_completed_successfully}, migrate: {condition: service_started}}
"""
    )
    j = judge.Judge(exp, 60, 0.0)
    assert sorted(j.step(0.0, {})) == ["migrate", "seed"]
    # migrate already finished (it started), seed still running: test waits
    assert j.step(1.0, {"seed": obs(), "migrate": obs(EXITED, 0)}) == []
    assert j.step(2.0, {"seed": obs(EXITED, 0), "migrate": obs(EXITED, 0)}) == ["test"]


def test_an_orchestrator_exiting_non_zero_fails_the_run():
    j = started_all()
    j.step(4.0, everything_running(check=obs(EXITED, 3)))
    assert j.verdict["result"] == judge.FAILED
    assert j.verdict["service"] == "check" and j.verdict["reason"] == "orchestrator check exited with 3"


def test_the_run_passes_when_every_orchestrator_exited_0_while_the_others_still_run():
    exp = read(
        """
services:
  robot: {image: reg/robot:1}
  a: {image: reg/a:1, labels: {isaacsim.fleet/test-orchestrator: "true"}}
  b: {image: reg/b:1, labels: {isaacsim.fleet/test-orchestrator: "true"}}
"""
    )
    j = judge.Judge(exp, 60, 0.0)
    assert sorted(j.step(0.0, {})) == ["a", "b", "robot"]
    j.step(1.0, {"robot": obs(), "a": obs(EXITED, 0), "b": obs()})
    assert j.verdict is None  # b still runs
    j.step(2.0, {"robot": obs(), "a": obs(EXITED, 0), "b": obs(EXITED, 0)})
    assert j.verdict["result"] == judge.PASSED and j.verdict["reason"] == "every orchestrator exited 0 (a, b)"


def test_a_non_orchestrator_failing_without_restart_fails_the_run():
    j = started_all()
    j.step(4.0, everything_running(planner=obs(EXITED, 1)))
    assert j.verdict["result"] == judge.FAILED and j.verdict["reason"] == "planner exited with 1"


def test_a_non_orchestrator_with_restart_is_restarted_and_the_run_goes_on():
    j = started_all()
    j.step(4.0, everything_running(recorder=obs(RESTARTING, 2, restarts=1)))
    j.step(5.0, everything_running(recorder=obs(RUNNING, None, restarts=1)))
    assert j.verdict is None
    assert (4.0, "recorder", "restarted by its restart policy (1 so far)") in j.events
    j.step(6.0, everything_running(recorder=obs(restarts=1), check=obs(EXITED, 0)))
    assert j.verdict["result"] == judge.PASSED


def test_a_restarting_service_whose_retries_are_spent_fails_the_run():
    j = started_all()
    # systemd refused the next start (StartLimitBurst): the unit stays down with the last exit code
    j.step(4.0, everything_running(recorder=obs(EXITED, 2, restarts=3)))
    assert j.verdict["reason"] == "recorder exited with 2 after 3 restarts"


def test_a_zero_exit_of_a_non_orchestrator_is_ignored():
    j = started_all()
    j.step(4.0, everything_running(recorder=obs(EXITED, 0)))
    assert j.verdict is None
    assert any(e[1] == "recorder" and "ignored" in e[2] for e in j.events)


def test_a_service_is_not_judged_before_it_starts_so_a_late_dependency_fails_nothing():
    j = judge.Judge(ROBOT, 60, 0.0)
    j.step(0.0, {"sim": obs()})
    # db is slow to get healthy: planner and check wait and nothing fails, however long it takes
    for t in range(1, 30):
        assert j.step(float(t), {"sim": obs(), "db": obs(health="starting"), "recorder": obs()}) == []
    assert j.verdict is None and "planner" not in j.started


def test_orchestrators_never_restart_and_a_docker_failure_is_an_error_not_a_failure():
    exp = read(
        """
services:
  check:
    image: reg/check:1
    restart: always
    labels: {isaacsim.fleet/test-orchestrator: "true"}
"""
    )
    assert exp["services"]["check"]["restart"] == "no"
    j = judge.Judge(exp, 60, 0.0)
    j.step(0.0, {})
    j.step(1.0, {"check": obs(EXITED, 125)})
    assert j.verdict["result"] == judge.ERROR
    assert "docker could not run the container" in j.verdict["reason"]


def test_the_run_times_out_naming_the_orchestrators_still_running():
    j = started_all(timeout=10)
    j.step(9.9, everything_running())
    assert j.verdict is None
    j.step(10.0, everything_running())
    assert j.verdict["result"] == judge.TIMEOUT
    assert j.verdict["reason"] == "timed out after 10 s with check still running"


def test_the_simulator_going_down_fails_the_run():
    j = started_all()
    j.step(4.0, everything_running(sim=obs(EXITED)))
    assert j.verdict["result"] == judge.FAILED and j.verdict["service"] == "sim"


def test_a_killed_container_says_by_which_signal_and_nothing_is_decided_twice():
    j = started_all()
    j.step(4.0, everything_running(planner=obs(EXITED, 137)))
    assert j.verdict["reason"] == "planner exited with 137 (killed by signal 9)"
    first = dict(j.verdict)
    assert j.step(5.0, everything_running(check=obs(EXITED, 0))) == []
    assert j.verdict == first


def test_a_unit_whose_container_is_not_up_yet_is_not_started_for_its_dependents():
    j = judge.Judge(ROBOT, 60, 0.0)
    j.step(0.0, {"sim": obs()})
    j.step(1.0, everything_running(planner=judge.observation(), check=judge.observation()))
    # check depends on planner (service_started): planner's unit is starting, no container yet
    assert j.step(2.0, everything_running(planner=judge.observation(STARTING), check=judge.observation())) == []
    assert j.step(3.0, everything_running(check=judge.observation())) == ["check"]


def test_a_dependency_that_finished_without_its_condition_fails_the_run_at_once():
    j = judge.Judge(ROBOT, 60, 0.0)
    j.step(0.0, {"sim": obs()})
    # db exits 0 before it was ever healthy: planner would wait for ever, as compose refuses to
    j.step(1.0, {"sim": obs(), "db": obs(EXITED, 0), "recorder": obs()})
    assert j.verdict["result"] == judge.FAILED
    assert j.verdict["reason"] == "planner cannot start: db exited with 0 and service_healthy will never hold"


def test_a_timeout_names_who_still_ran_and_who_never_started():
    j = judge.Judge(ROBOT, 5, 0.0)
    j.step(0.0, {"sim": obs()})
    j.step(5.0, {"sim": obs(), "db": obs(health="starting"), "recorder": obs()})
    assert j.verdict["reason"] == ("timed out after 5 s, never started (their depends_on did not hold): check, planner")


def test_the_runner_s_own_trouble_is_an_error_decided_once():
    j = started_all()
    j.fail(4.0, "planner", "systemd would not start planner")
    j.fail(5.0, None, "later")
    assert j.verdict["result"] == judge.ERROR and j.verdict["reason"] == "systemd would not start planner"
