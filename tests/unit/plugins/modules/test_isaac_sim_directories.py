"""The isaac_sim_directories module on a temporary directory, as the current user."""

from __future__ import annotations

import os
import stat

from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_directories
from ansible_collections.isaacsim.fleet.tests.unit.helpers import run_module


def args_for(tmp_path, **over):
    paths = [str(tmp_path / "instance-0"), str(tmp_path / "instance-0" / "cache")]
    return dict({"paths": paths, "owner": os.getuid(), "group": os.getgid(), "mode": "0750"}, **over)


def test_creates_then_has_nothing_to_do(tmp_path, capsys):
    result = run_module(isaac_sim_directories.main, args_for(tmp_path), capsys)
    assert result["changed"] and [c[1] for c in result["changes"]] == ["create", "create"]
    assert stat.S_IMODE(os.stat(tmp_path / "instance-0" / "cache").st_mode) == 0o750
    assert run_module(isaac_sim_directories.main, args_for(tmp_path), capsys)["changed"] is False


def test_check_mode_with_diff_creates_nothing(tmp_path, capsys):
    result = run_module(
        isaac_sim_directories.main, args_for(tmp_path, _ansible_check_mode=True, _ansible_diff=True), capsys
    )
    assert result["changed"] and "create needed" in result["diff"]["before"]
    assert not (tmp_path / "instance-0").exists()


def test_a_mode_that_is_not_octal_is_refused(tmp_path, capsys):
    result = run_module(isaac_sim_directories.main, args_for(tmp_path, mode="rwx"), capsys)
    assert result["failed"] and "is not an octal mode" in result["msg"]
