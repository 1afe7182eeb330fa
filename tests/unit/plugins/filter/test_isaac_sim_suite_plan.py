"""The isaac_sim_suite_plan filter, as playbooks/test_suite.yml calls it: test_suite_file |
isaac_sim_suite_plan(what each host can give, test_suite_dir/suite.json when re-running the failed
ones), on real suite and compose files (the fixtures' experiences, copied beside the suite)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
import yaml
from ansible.errors import AnsibleFilterError
from ansible_collections.isaacsim.fleet.plugins.filter.isaac_sim_suite_plan import FilterModule
from ansible_collections.isaacsim.fleet.plugins.filter.isaac_sim_suite_report import suite_report

FIXTURES = Path(__file__).resolve().parents[3] / "fixtures" / "experiences"
# a compose file with a Go template in it (docker's --format): data, never an Ansible template
GPU = """
services:
  check:
    image: reg/check:1
    labels: {isaacsim.fleet/test-orchestrator: "true"}
    healthcheck:
      test: ["CMD-SHELL", "docker inspect --format '{{.State.Health.Status}}' robot | grep -q healthy"]
    deploy:
      resources:
        reservations:
          devices: [{capabilities: [gpu], count: 2}]
"""


def plan(path, hosts, previous=None):
    return FilterModule().filters()["isaac_sim_suite_plan"](str(path), hosts, previous)


def caps(parallel=2, gpus=0, instances=0) -> dict:
    """One host's entry of the playbook's __caps."""
    return {"parallel": parallel, "gpus": gpus, "instances": instances}


@pytest.fixture()
def suite_dir(tmp_path, monkeypatch):
    """A suite's directory with the fixtures' experiences under experiences/; the playbook runs elsewhere."""
    where = tmp_path / "suites"
    shutil.copytree(FIXTURES, where / "experiences")
    (where / "experiences" / "gpu.yml").write_text(GPU)
    monkeypatch.chdir(tmp_path)
    return where


def write(path: Path, suite) -> Path:
    path.write_text(yaml.safe_dump(suite) if isinstance(suite, dict) else suite)
    return path


NIGHTLY = {
    "environment": {"IMAGE": "reg/standin:1"},
    "timeout": 120,
    "experiences": [
        {"file": "experiences/pass.yml", "repeat": 3},
        {"file": "experiences/crash.yml", "parameters": [{"CRASH_RESTART": "no"}, {"CRASH_RESTART": "on-failure"}]},
        {"file": "experiences/sim.yml", "timeout": 30},
        "experiences/gpu.yml",
    ],
}


def test_every_run_goes_to_a_host_that_can_give_it_what_it_needs_the_least_loaded_first(suite_dir):
    suite = write(suite_dir / "nightly.yml", NIGHTLY)
    found = plan(suite, {"gpu-1": caps(instances=1), "gpu-2": caps(gpus=2), "gpu-3": caps(parallel=1)})
    assert found["errors"] == [] and found["runs"] == 7
    assert {host: [r["title"] for r in runs] for host, runs in found["plan"].items()} == {
        # the only host lending an instance takes the run that borrows one
        "gpu-1": ["pass#1", "crash[CRASH_RESTART=no]", "sim"],
        # the only host with two GPUs takes the run that reserves them
        "gpu-2": ["pass#2", "crash[CRASH_RESTART=on-failure]", "gpu"],
        "gpu-3": ["pass#3"],
    }
    runs = {r["title"]: r for runs in found["plan"].values() for r in runs}
    pass_1, sim, gpu = runs["pass#1"], runs["sim"], runs["gpu"]
    # files are found beside the suite, read as the fleet runs them, whatever the working directory
    assert pass_1["file"] == str(suite_dir / "experiences" / "pass.yml")
    assert pass_1["compose"] == yaml.safe_load((suite_dir / "experiences" / "pass.yml").read_text())
    assert (pass_1["timeout"], sim["timeout"], pass_1["environment"]) == (120.0, 30.0, {"IMAGE": "reg/standin:1"})
    assert runs["crash[CRASH_RESTART=no]"]["environment"] == {"IMAGE": "reg/standin:1", "CRASH_RESTART": "no"}
    assert (sim["simulator"], sim["gpus"], gpu["simulator"], gpu["gpus"]) == (True, 0, False, 2)
    assert gpu["compose"]["services"]["check"]["healthcheck"]["test"][1].startswith(
        "docker inspect --format '{{.State.Health.Status}}' robot"
    )
    assert len({r["key"] for r in runs.values()}) == 7


def test_a_run_no_host_can_take_is_named_with_what_it_lacks(suite_dir):
    suite = write(suite_dir / "nightly.yml", NIGHTLY)
    found = plan(suite, {"gpu-1": caps(gpus=1), "gpu-2": caps()})
    assert found["runs"] == 7
    assert found["errors"] == [
        "sim: no host can give it a ready instance to borrow. Fix: ask for less, or add hosts that have it.",
        "gpu: no host can give it 2 GPU(s) (the most any host has is 1). Fix: ask for less, or add hosts that have it.",
    ]


def test_one_bad_file_stops_the_suite_before_any_run_is_planned(suite_dir):
    suite = write(
        suite_dir / "broken.yml",
        {
            "environment": {"IMAGE": "reg/standin:1"},
            "retries": 2,
            "experiences": ["experiences/pass.yml", "experiences/bad.yml", {"file": "experiences/gone.yml"}],
        },
    )
    found = plan(suite, {"gpu-1": caps(), "gpu-2": caps()})
    assert found["plan"] == {"gpu-1": [], "gpu-2": []} and found["runs"] == 1
    bad, gone = suite_dir / "experiences" / "bad.yml", suite_dir / "experiences" / "gone.yml"
    assert found["errors"][0] == (
        "test_suite: retries is not a setting of a suite. Fix: experiences, environment or timeout."
    )
    assert found["errors"][1].startswith(f"test_suite.experiences[1] ({bad}): bad: ")
    assert found["errors"][-1] == (
        f"test_suite.experiences[2].file: {gone} cannot be read ([Errno 2] No such file or directory: '{gone}'). "
        "Fix: correct the path."
    )
    assert write(suite_dir / "empty.yml", "") and plan(suite_dir / "empty.yml", {"gpu-1": caps()})["errors"] == [
        "test_suite: no experiences. Fix: give a list under experiences, each with a file."
    ]


def test_a_suite_file_that_cannot_be_read_names_test_suite_file(suite_dir):
    gone = suite_dir / "nightly.yml"
    with pytest.raises(AnsibleFilterError) as failed:
        plan(gone, {"gpu-1": caps()})
    assert failed.value.message == (
        f"test_suite_file: {gone} cannot be read ([Errno 2] No such file or directory: '{gone}'). "
        "Fix: give the suite's path."
    )
    write(gone, "experiences: [pass.yml\n")
    with pytest.raises(AnsibleFilterError) as failed:
        plan(gone, {"gpu-1": caps()})
    assert failed.value.message.startswith(f"test_suite_file: {gone} cannot be read (not YAML: ")
    assert failed.value.message.endswith("). Fix: give the suite's path.")


def test_a_re_run_plans_only_the_runs_that_did_not_pass_in_the_previous_suite_json(suite_dir):
    suite = write(suite_dir / "nightly.yml", NIGHTLY)
    hosts = {"gpu-1": caps(instances=1), "gpu-2": caps(gpus=2)}
    first = plan(suite, hosts)
    verdicts = {"pass#1": "passed", "pass#2": "failed", "crash[CRASH_RESTART=no]": "timeout", "sim": "passed"}
    results = [
        {
            "title": run["title"],
            "host": host,
            "run": f"{run['key']}-x",
            "verdict": {"result": verdicts[run["title"]], "service": "check", "reason": "as judged", "seconds": 9.5},
        }
        for host, runs in first["plan"].items()
        for run in runs
        if run["title"] in verdicts
    ]
    # the other runs came back with no result: the report makes them errors
    report = suite_report(results, 60.0, [], first["plan"], {"gpu-2": "the host did not answer"})
    runs_dir = suite_dir / "test-runs"
    runs_dir.mkdir()
    # as the playbook writes it ({'results': __report.results} | to_nice_json)
    (runs_dir / "suite.json").write_text(json.dumps({"results": report["results"]}, indent=4))

    again = plan(suite, hosts, str(runs_dir / "suite.json"))
    assert again["errors"] == [] and again["runs"] == 5
    assert sorted(r["title"] for runs in again["plan"].values() for r in runs) == [
        "crash[CRASH_RESTART=no]",
        "crash[CRASH_RESTART=on-failure]",
        "gpu",
        "pass#2",
        "pass#3",
    ]


def test_previous_results_that_cannot_be_read_name_test_suite_rerun_failed(suite_dir):
    suite = write(suite_dir / "nightly.yml", NIGHTLY)
    previous = suite_dir / "test-runs" / "suite.json"
    reasons = {
        # the first re-run asked for before any suite wrote there
        None: f"[Errno 2] No such file or directory: '{previous}'",
        "": "Expecting value: line 1 column 1 (char 0)",
        "[]": "not a suite's results: a list of runs, each with its title, under results",
        '{"results": null}': "not a suite's results: a list of runs, each with its title, under results",
        '{"results": [{"verdict": {"result": "passed"}}]}': (
            "not a suite's results: a list of runs, each with its title, under results"
        ),
    }
    for text, reason in reasons.items():
        if text is not None:
            previous.parent.mkdir(exist_ok=True)
            previous.write_text(text)
        with pytest.raises(AnsibleFilterError) as failed:
            plan(suite, {"gpu-1": caps()}, str(previous))
        assert failed.value.message == (
            f"test_suite_rerun_failed: the previous results {previous} cannot be read ({reason}). "
            "Fix: run the whole suite."
        ), text


def test_a_wrong_timeout_is_named_where_it_is_set(suite_dir):
    def errors(suite: dict) -> list:
        found = plan(write(suite_dir / "timeouts.yml", suite), {"gpu-1": caps(instances=1)})
        assert found["plan"] == {"gpu-1": []}
        return found["errors"]

    entries = ["experiences/pass.yml", {"file": "experiences/sim.yml", "timeout": 30}]
    env = {"IMAGE": "reg/standin:1"}
    # the suite's own, which every entry without one of its own takes: said once, of the suite
    assert errors({"environment": env, "timeout": "soon", "experiences": entries}) == [
        "test_suite.timeout: 'soon'. Fix: a number of seconds above 0."
    ]
    assert errors({"environment": env, "timeout": 0, "experiences": entries}) == [
        "test_suite.timeout: 0. Fix: a number of seconds above 0."
    ]
    entries[1]["timeout"] = -5
    assert errors({"environment": env, "experiences": entries}) == [
        "test_suite.experiences[1].timeout: -5. Fix: a number of seconds above 0."
    ]
