"""The isaac_sim_host_service module on files in a temporary directory, systemctl answered as
systemd 252 answers `show` (a unit that is not loaded: inactive, no unit file)."""

from __future__ import annotations

import os
import stat

import pytest
from ansible.module_utils import basic
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_host_service
from ansible_collections.isaacsim.fleet.tests.unit.helpers import run_module


@pytest.fixture
def systemctl(monkeypatch):
    """Records every systemctl call and keeps the unit's state as systemd would."""
    unit = {"ActiveState": "inactive", "UnitFileState": "", "LoadState": "not-found", "Triggers": "", "fail": None}
    calls = []

    def run_command(self, args, **kwargs):
        verb = args[1]
        calls.append(verb)
        unit.setdefault("argvs", []).append(list(args))
        if verb == "show":
            keys = [args[i + 1] for i, a in enumerate(args) if a == "-p"]
            return 0, "".join(f"{k}={unit[k]}\n" for k in keys), ""
        if verb == unit["fail"]:
            return 1, "", "Job for x.service failed because the control process exited with error code."
        unit.update(
            {
                "start": {"ActiveState": "active"},
                "stop": {"ActiveState": "inactive"},
                "enable": {"UnitFileState": "enabled"},
                "disable": {"UnitFileState": "disabled"},
            }.get(verb, {})
        )
        return 0, "", ""

    monkeypatch.setattr(basic.AnsibleModule, "run_command", run_command)
    monkeypatch.setattr(basic.AnsibleModule, "get_bin_path", lambda self, name, *a, **kw: f"/usr/bin/{name}")
    return unit, calls


def args(tmp_path, **over):
    base = {
        "name": "x.service",
        "files": {
            str(tmp_path / "x.service"): {"content": "[Service]\nExecStart=/bin/true\n"},
            str(tmp_path / "x-server"): {"content": "#!/bin/sh\n", "mode": "0755"},
        },
        "directories": [{"path": str(tmp_path / "state"), "uid": os.getuid(), "gid": os.getgid(), "mode": "0700"}],
    }
    base.update(over)
    return base


def test_started_writes_reloads_enables_starts_then_a_rerun_changes_nothing(tmp_path, systemctl, capsys):
    unit, calls = systemctl
    result = run_module(isaac_sim_host_service.main, args(tmp_path), capsys)
    assert result["changed"] and result["actions"] == ["directories", "write", "daemon-reload", "enable", "start"]
    assert calls == ["show", "daemon-reload", "enable", "start"]
    assert stat.S_IMODE(os.stat(tmp_path / "x-server").st_mode) == 0o755
    assert stat.S_IMODE(os.stat(tmp_path / "state").st_mode) == 0o700
    again = run_module(isaac_sim_host_service.main, args(tmp_path), capsys)
    assert again["changed"] is False and again["actions"] == [] and again["changed_files"] == []


def test_a_changed_script_restarts_without_a_daemon_reload(tmp_path, systemctl, capsys):
    unit, calls = systemctl
    run_module(isaac_sim_host_service.main, args(tmp_path), capsys)
    calls.clear()
    changed = args(tmp_path)
    changed["files"][str(tmp_path / "x-server")]["content"] = "#!/bin/sh\nexit 0\n"
    result = run_module(isaac_sim_host_service.main, changed, capsys)
    assert result["actions"] == ["write", "restart"] and result["changed_files"] == [str(tmp_path / "x-server")]
    assert calls == ["show", "restart"]


def test_check_mode_and_diff_change_nothing(tmp_path, systemctl, capsys):
    unit, calls = systemctl
    result = run_module(
        isaac_sim_host_service.main, {**args(tmp_path), "_ansible_check_mode": True, "_ansible_diff": True}, capsys
    )
    assert result["changed"] and result["diff"]["before"] == ""
    assert str(tmp_path / "x.service") in result["diff"]["after"]
    assert calls == ["show"] and sorted(os.listdir(tmp_path)) == []


def test_absent_stops_disables_and_removes_files_but_keeps_directories(tmp_path, systemctl, capsys):
    unit, calls = systemctl
    run_module(isaac_sim_host_service.main, args(tmp_path), capsys)
    (tmp_path / "extra").mkdir()
    calls.clear()
    result = run_module(
        isaac_sim_host_service.main, {**args(tmp_path), "state": "absent", "remove": [str(tmp_path / "extra")]}, capsys
    )
    assert result["actions"] == ["stop", "reset-failed", "disable", "remove", "daemon-reload"]
    assert calls == ["show", "stop", "reset-failed", "disable", "daemon-reload"]
    assert ["/usr/bin/systemctl", "stop", "x.service"] in unit["argvs"]
    assert sorted(os.listdir(tmp_path)) == ["state"]


def test_a_timer_going_away_stops_the_service_it_triggers_in_the_same_call(tmp_path, systemctl, capsys):
    unit, calls = systemctl
    timer = {"name": "x.timer", "files": {str(tmp_path / "x.timer"): {"content": "[Timer]\n"}}}
    run_module(isaac_sim_host_service.main, args(tmp_path, **timer), capsys)
    unit["Triggers"] = "x.service"
    calls.clear()
    result = run_module(isaac_sim_host_service.main, {**args(tmp_path, **timer), "state": "absent"}, capsys)
    assert result["actions"] == ["stop", "reset-failed", "disable", "remove", "daemon-reload"]
    assert calls == ["show", "stop", "reset-failed", "reset-failed", "disable", "daemon-reload"]
    assert ["/usr/bin/systemctl", "stop", "x.timer", "x.service"] in unit["argvs"]
    # a run of the service stopped mid-way is not left listed as failed once its file is gone
    assert ["/usr/bin/systemctl", "reset-failed", "x.service"] in unit["argvs"]


@pytest.mark.parametrize(
    "over, message",
    [
        ({"files": {"relative/x.service": {"content": ""}}}, "'relative/x.service' is not an absolute path"),
        ({"files": {"/etc/x.service": {"mode": "0644"}}}, "files./etc/x.service: no content"),
    ],
)
def test_bad_files_are_refused_before_systemctl_is_asked(tmp_path, systemctl, capsys, over, message):
    unit, calls = systemctl
    result = run_module(isaac_sim_host_service.main, args(tmp_path, **over), capsys)
    assert result["failed"] and message in result["msg"] and "Fix:" in result["msg"]
    assert calls == [] and os.listdir(tmp_path) == []


def test_a_failed_start_names_the_unit_and_where_to_look(tmp_path, systemctl, capsys):
    unit, calls = systemctl
    unit["fail"] = "start"
    result = run_module(isaac_sim_host_service.main, args(tmp_path), capsys)
    assert result["failed"] and result["msg"].startswith("systemctl start x.service failed: Job for x.service failed")
    assert "journalctl -u x.service" in result["msg"]
    assert result["actions"][-1] == "start" and len(result["changed_files"]) == 2
