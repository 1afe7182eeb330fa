"""isaac-sim-ready, the readiness gate, run by a real bash with a recording Docker stand-in."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

FILES = Path(__file__).resolve().parents[4] / "roles" / "isaac_sim" / "files"


def gate(tmp_path, pattern):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    # a container that runs and never prints its ready line
    docker = bin_dir / "docker"
    docker.write_text('#!/bin/sh\n[ "$1" = inspect ] && echo running\nexit 0\n')
    docker.chmod(0o755)
    env = dict(
        os.environ,
        PATH=f"{bin_dir}:{os.environ['PATH']}",
        ISAAC_SIM_CONTAINER="isaac-sim-1",
        ISAAC_SIM_READY_MARKER=str(tmp_path / "instance-1.ready"),
        ISAAC_SIM_READY_TIMEOUT="1",
        ISAAC_SIM_READY_PATTERN=pattern,
    )
    return subprocess.run(
        ["bash", str(FILES / "isaac-sim-ready")], capture_output=True, text=True, env=env, timeout=30, check=False
    )


def test_the_deadline_names_what_it_waited_for_once(tmp_path):
    done = gate(tmp_path, r"App is loaded\.")
    assert done.returncode == 1
    assert r"isaac-sim-1 was not ready within 1 s (waiting for /App is loaded\./ in its output)" in done.stderr
    assert done.stderr.count("App is loaded") == 1
    healthy = gate(tmp_path, "")
    assert "(waiting for a running, healthy container)" in healthy.stderr


def test_a_start_ready_within_a_second_is_seen_at_the_next_quarter_second(tmp_path):
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    looks = tmp_path / "looks"
    # a container that prints its ready line from the third look at its logs on
    (bin_dir / "docker").write_text(
        "#!/bin/sh\n"
        '[ "$1" = inspect ] && { echo running; exit 0; }\n'
        f'echo x >> {looks}; [ "$(wc -l < {looks})" -ge 3 ] && echo "Isaac Sim Full App is loaded."\n'
        "exit 0\n"
    )
    # the gate's waits, written down (and taken for real)
    (bin_dir / "sleep").write_text(f'#!/bin/sh\necho "$1" >> {tmp_path / "sleeps"}\nexec /bin/sleep "$1"\n')
    for tool in ("docker", "sleep"):
        (bin_dir / tool).chmod(0o755)
    env = dict(
        os.environ,
        PATH=f"{bin_dir}:{os.environ['PATH']}",
        ISAAC_SIM_CONTAINER="isaac-sim-1",
        ISAAC_SIM_READY_MARKER=str(tmp_path / "instance-1.ready"),
        ISAAC_SIM_READY_TIMEOUT="60",
        ISAAC_SIM_READY_PATTERN=r"App is loaded\.",
    )
    done = subprocess.run(
        ["bash", str(FILES / "isaac-sim-ready")], capture_output=True, text=True, env=env, timeout=30, check=False
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout == "isaac-sim-1 is ready\n"
    assert (tmp_path / "sleeps").read_text().split() == ["0.25", "0.25"]
    assert (tmp_path / "instance-1.ready").read_text().strip().isdigit()
