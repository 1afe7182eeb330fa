"""The isaac_sim_experience module end to end: its argument spec, the one call into
runs/runner.py and how it exits, against the scripted host of test_runner."""

from __future__ import annotations

import json

import pytest
import yaml
from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import runner
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_experience
from ansible_collections.isaacsim.fleet.tests.unit.helpers import run_module
from ansible_collections.isaacsim.fleet.tests.unit.plugins.module_utils.runs.test_runner import PAIR, Host, binder

RUN = "pair-20261124-0000-ab12"


@pytest.fixture()
def host(tmp_path, monkeypatch):
    """The module's host: scripted systemd and Docker, bound with the module's check mode; its
    warnings in host.warnings (where the module puts warnings depends on what else the test
    process imported: ansible-core 2.19 sends them to the controller's display once it is loaded)."""
    host = Host(tmp_path)
    host.warnings = []

    monkeypatch.setattr(runner, "bind", binder(host, host.warnings.append))
    return host


def args(tmp_path, **over) -> dict:
    base = {"compose": PAIR, "name": "pair", "gpus": ["0"], "data_root": str(tmp_path), "poll": 0.1}
    base.update(over)
    return base


def test_a_run_exits_with_its_verdict_and_its_bundle(host, tmp_path, capsys):
    compose = yaml.safe_load(yaml.safe_dump(PAIR))
    compose["services"]["check"]["pull_policy"] = "always"
    result = run_module(isaac_sim_experience.main, args(tmp_path, compose=compose), capsys)
    assert result["changed"] is True and result["run"] == RUN
    assert result["verdict"]["result"] == "passed" and result["verdict"]["service"] is None
    assert result["directory"] == f"{tmp_path}/runs/{RUN}" and result["directories"] == [result["directory"]]
    assert result["bundle"].startswith(f"{tmp_path}/runs/bundle-") and result["borrowed_instance"] is None
    assert sorted(result["services"]) == ["check", "robot"] and "junit.xml" in result["artefacts"]
    # what the fleet ignores comes back, and as a warning
    assert (
        host.warnings
        == result["ignored"]
        == ["pair: services.check.pull_policy: ignored; images are pulled before the run, once per host."]
    )


def test_secrets_stay_out_of_the_result(host, tmp_path, capsys):
    result = run_module(isaac_sim_experience.main, args(tmp_path, secret_environment={"TOKEN": "s3cr3t-value"}), capsys)
    assert result["verdict"]["result"] == "passed"
    assert "s3cr3t-value" not in json.dumps(result)
    # the container gets it, from a file only root reads
    env_file = f"/run/isaac-sim/runs/{RUN}/robot.env"
    assert "TOKEN=s3cr3t-value" in host.files[env_file] and host.modes[env_file] == 0o600


def test_check_mode_starts_nothing(host, tmp_path, capsys):
    result = run_module(isaac_sim_experience.main, args(tmp_path, _ansible_check_mode=True), capsys)
    assert result["changed"] is True and result["order"] == ["robot", "check"] and "verdict" not in result
    assert host.calls == []


def test_a_simulator_option_outside_its_choices_is_refused_by_the_argument_spec(host, tmp_path, capsys):
    result = run_module(isaac_sim_experience.main, args(tmp_path, simulator="shared"), capsys)
    assert result["failed"] and "simulator" in result["msg"] and "borrow, dedicated" in result["msg"]


def test_bad_input_fails_on_the_real_host_before_anything_is_touched(tmp_path, capsys):
    # runner.bind as the module has it: nothing of the host is asked before the input is checked
    result = run_module(isaac_sim_experience.main, args(tmp_path, timeout=0, run="x y"), capsys)
    assert result["failed"] is True
    assert result["errors"] == [
        "run: 'x y' is not a run name. Fix: lower case letters, digits and dashes, 63 at most.",
        "timeout: 0. Fix: a number of seconds above 0.",
    ]
    assert result["msg"] == " ".join(result["errors"])
    assert result["run"] == "x y" and result["recovered"] == [] and result["borrowed_instance"] is None
