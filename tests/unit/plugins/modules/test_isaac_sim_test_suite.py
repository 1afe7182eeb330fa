"""The isaac_sim_test_suite module end to end: its argument spec, the one call into
runs/runner.py and how it exits, against the scripted host of test_runner."""

from __future__ import annotations

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import runner
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_test_suite
from ansible_collections.isaacsim.fleet.tests.unit.helpers import run_module
from ansible_collections.isaacsim.fleet.tests.unit.plugins.module_utils.runs.test_runner import PAIR, Host, binder


@pytest.fixture()
def host(tmp_path, monkeypatch):
    """The module's host: scripted systemd and Docker, in the module's check mode."""
    host = Host(tmp_path)
    monkeypatch.setattr(runner, "bind", binder(host, lambda text: None))
    return host


def runs(*keys) -> list:
    return [
        {"key": k, "title": f"pair#{n + 1}", "experience": "pair", "compose": PAIR, "timeout": 60}
        for n, k in enumerate(keys)
    ]


def test_a_share_exits_with_a_result_per_run_in_order_and_one_bundle(host, tmp_path, capsys):
    args = {"runs": runs("p-1-1", "p-1-2"), "gpus": ["0", "1"], "data_root": str(tmp_path)}
    result = run_module(isaac_sim_test_suite.main, args, capsys)
    assert result["changed"] is True
    assert [(r["title"], r["run"], r["verdict"]["result"]) for r in result["results"]] == [
        ("pair#1", "p-1-1-20261124-0000-ab12", "passed"),
        ("pair#2", "p-1-2-20261124-0000-ab12", "passed"),
    ]
    assert result["directories"] == [
        f"{tmp_path}/runs/p-1-1-20261124-0000-ab12",
        f"{tmp_path}/runs/p-1-2-20261124-0000-ab12",
    ]
    assert result["bundle"].endswith(".tar.gz") and result["recovered"] == [] and result["expired"] == []


def test_check_mode_runs_nothing(host, tmp_path, capsys):
    args = {"runs": runs("p-1-1"), "data_root": str(tmp_path), "_ansible_check_mode": True}
    result = run_module(isaac_sim_test_suite.main, args, capsys)
    assert result["changed"] is True and result["results"] == [] and result["errors"] == []
    assert host.calls == []
    # nothing to run: nothing would change
    result = run_module(isaac_sim_test_suite.main, dict(args, runs=[]), capsys)
    assert result["changed"] is False


def test_a_share_with_no_run_slot_fails_on_the_real_host_before_anything_is_touched(tmp_path, capsys):
    result = run_module(isaac_sim_test_suite.main, {"runs": runs("p-1-1"), "parallel": 0}, capsys)
    assert result["failed"] is True and result["msg"] == "parallel: 0. Fix: 1 or more runs at once."


def test_runs_are_a_required_list(tmp_path, capsys):
    result = run_module(isaac_sim_test_suite.main, {"parallel": 1}, capsys)
    assert result["failed"] and result["msg"] == "missing required arguments: runs"
