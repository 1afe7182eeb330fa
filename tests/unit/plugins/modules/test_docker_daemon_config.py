"""The docker_daemon_config module on a daemon.json in a temporary directory."""

from __future__ import annotations

import json
import os
import stat

from ansible_collections.isaacsim.fleet.plugins.modules import docker_daemon_config
from ansible_collections.isaacsim.fleet.tests.unit.helpers import run_module

RUNTIME = {"runtimes": {"nvidia": {"path": "nvidia-container-runtime", "args": []}}}


def test_merges_writes_once_and_keeps_other_keys(tmp_path, capsys):
    path = tmp_path / "docker" / "daemon.json"
    path.parent.mkdir()
    path.write_text('{"log-driver": "local"}')
    result = run_module(docker_daemon_config.main, {"path": str(path), "settings": RUNTIME}, capsys)
    assert result["changed"] and result["config"]["log-driver"] == "local"
    assert json.loads(path.read_text())["runtimes"]["nvidia"]["path"] == "nvidia-container-runtime"
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o644
    again = run_module(docker_daemon_config.main, {"path": str(path), "settings": RUNTIME}, capsys)
    assert again["changed"] is False


def test_check_mode_shows_the_diff_and_writes_nothing(tmp_path, capsys):
    path = tmp_path / "daemon.json"
    args = {"path": str(path), "settings": RUNTIME, "_ansible_check_mode": True, "_ansible_diff": True}
    result = run_module(docker_daemon_config.main, args, capsys)
    assert result["changed"] and result["diff"]["before"] == "" and "nvidia" in result["diff"]["after"]
    assert not path.exists()


def test_a_file_that_is_not_json_is_left_alone(tmp_path, capsys):
    path = tmp_path / "daemon.json"
    path.write_text("{broken")
    result = run_module(docker_daemon_config.main, {"path": str(path), "settings": RUNTIME}, capsys)
    assert result["failed"] and path.read_text() == "{broken"


def test_no_settings_write_no_file_and_the_restart_marker_is_reported(tmp_path, capsys):
    path, marker = tmp_path / "daemon.json", tmp_path / "restart-pending"
    args = {"path": str(path), "settings": {}, "restart_marker": str(marker)}
    result = run_module(docker_daemon_config.main, args, capsys)
    assert result["changed"] is False and not path.exists() and result["restart_noted"] is False
    marker.write_text("")
    assert run_module(docker_daemon_config.main, args, capsys)["restart_noted"] is True
    # without the option the module says nothing about it
    assert "restart_noted" not in run_module(docker_daemon_config.main, {"path": str(path), "settings": {}}, capsys)


# a package query that knows docker.io only, as vars/<OS family>.yml's query prints it
QUERY = ["sh", "-c", 'for p; do [ "$p" = docker.io ] && echo "$p ii"; done; exit 0', "query"]


def test_a_missing_package_holds_the_merge_and_says_what_is_missing(tmp_path, capsys):
    path = tmp_path / "daemon.json"
    args = {"path": str(path), "settings": RUNTIME, "packages": ["docker.io", "docker-ce"], "installed_query": QUERY}
    result = run_module(docker_daemon_config.main, args, capsys)
    # the role installs them and calls again: nothing is written before Docker is there
    assert result["missing"] == ["docker-ce"] and result["changed"] is False and not path.exists()
    args["packages"] = ["docker.io"]
    result = run_module(docker_daemon_config.main, args, capsys)
    assert result["missing"] == [] and result["changed"] and path.exists()


def test_packages_without_their_query_are_refused_before_anything_is_read_or_written(tmp_path, capsys):
    path = tmp_path / "daemon.json"
    result = run_module(docker_daemon_config.main, {"path": str(path), "settings": RUNTIME, "packages": ["x"]}, capsys)
    assert result["failed"] and "installed_query" in result["msg"] and not path.exists()
