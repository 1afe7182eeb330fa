"""isaac-sim-cache-state, run by a real bash on real directories: warm when any cache holds a file."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout

FILES = Path(__file__).resolve().parents[4] / "roles" / "isaac_sim" / "files"


def state(tmp_path, caches) -> str:
    run_dir = tmp_path / "run"
    env = dict(
        os.environ,
        ISAAC_SIM_CACHE_STATE=str(run_dir / "instance-3.cache"),
        # as the env file has it, one shell-quoted word per directory
        ISAAC_SIM_CACHES=layout.join_args([str(c) for c in caches]),
    )
    done = subprocess.run(
        ["bash", str(FILES / "isaac-sim-cache-state")], capture_output=True, text=True, env=env, timeout=30, check=False
    )
    assert done.returncode == 0, done.stderr
    return (run_dir / "instance-3.cache").read_text()


def test_cold_until_a_cache_holds_a_file_then_warm(tmp_path):
    kit, shaders = tmp_path / "cache dir" / "kit", tmp_path / "ov $HOME"
    # a cache directory not made yet, then made but empty, with only empty subdirectories
    assert state(tmp_path, [kit, shaders]) == "cold\n"
    (shaders / "sub" / "deeper").mkdir(parents=True)
    kit.mkdir(parents=True)
    assert state(tmp_path, [kit, shaders]) == "cold\n"
    (shaders / "sub" / "deeper" / "shader.bin").write_bytes(b"x")
    assert state(tmp_path, [kit, shaders]) == "warm\n"
    # no caches named (an env file of an older version): cold, never a failed start
    assert state(tmp_path, []) == "cold\n"
