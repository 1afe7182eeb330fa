"""Merging settings into daemon.json (module_utils/host/daemon_json.py)."""

from __future__ import annotations

import json
import os

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import daemon_json

RUNTIME = {"runtimes": {"nvidia": {"path": "nvidia-container-runtime", "args": []}}}


def test_keeps_keys_it_does_not_own():
    current = '{"log-driver": "local", "runtimes": {"crun": {"path": "/usr/bin/crun"}}}'
    changed, _before, after = daemon_json.plan(current, RUNTIME, "/etc/docker/daemon.json")
    assert changed
    data = json.loads(after)
    assert data["log-driver"] == "local"
    assert data["runtimes"]["crun"] == {"path": "/usr/bin/crun"}
    assert data["runtimes"]["nvidia"]["path"] == "nvidia-container-runtime"


def test_second_run_changes_nothing_whatever_the_formatting():
    after = daemon_json.plan(None, RUNTIME, "p")[2]
    assert daemon_json.plan(after, RUNTIME, "p")[0] is False
    compact = json.dumps(json.loads(after), separators=(",", ":"))
    assert daemon_json.plan(compact, RUNTIME, "p")[0] is False


def test_missing_file_is_created():
    changed, before, after = daemon_json.plan(None, {"insecure-registries": ["10.0.0.1:5000"]}, "p")
    assert changed and before == ""
    assert json.loads(after) == {"insecure-registries": ["10.0.0.1:5000"]}


def test_lists_are_replaced_not_appended():
    changed, _before, after = daemon_json.plan('{"insecure-registries": ["a"]}', {"insecure-registries": ["b"]}, "p")
    assert json.loads(after)["insecure-registries"] == ["b"]


@pytest.mark.parametrize("text", ["{not json", "[1, 2]"])
def test_refuses_a_file_it_cannot_read(text):
    with pytest.raises(daemon_json.DaemonJsonError, match="left as it is"):
        daemon_json.plan(text, RUNTIME, "/etc/docker/daemon.json")


def test_merge_file_writes_through_the_move_given_and_never_in_check_mode(tmp_path):
    path = str(tmp_path / "docker" / "daemon.json")
    moved = []

    def move(tmp, dest):
        moved.append(dest)
        os.replace(tmp, dest)

    # nothing to merge into no file: no file
    assert daemon_json.merge_file(path, {}, False, move) == (False, "", "{}") and not os.path.exists(path)
    changed, _before, after = daemon_json.merge_file(path, {"log-driver": "journald"}, True, move)
    assert changed and json.loads(after) == {"log-driver": "journald"} and not os.path.exists(path)
    assert daemon_json.merge_file(path, {"log-driver": "journald"}, False, move)[0] and moved == [path]
    with open(path) as fh:
        assert json.load(fh) == {"log-driver": "journald"} and oct(os.stat(path).st_mode)[-3:] == "644"
    # as wanted already: not written again; no temporary file left beside it
    assert daemon_json.merge_file(path, {"log-driver": "journald"}, False, move)[0] is False and moved == [path]
    assert os.listdir(tmp_path / "docker") == ["daemon.json"]
