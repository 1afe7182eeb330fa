"""isaac-sim-ready, the readiness gate, run by a real bash with a recording Docker stand-in."""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

FILES = Path(__file__).resolve().parents[4] / "roles" / "isaac_sim" / "files"


# a container that runs and never prints its ready line
NEVER_READY = '#!/bin/sh\n[ "$1" = inspect ] && echo running\nexit 0\n'


def gate(tmp_path, pattern, timeout="1", mainpid=None, **tools):
    """The gate run against stand-in tools in PATH: docker (NEVER_READY unless given), and any other
    named here (name=script text)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir(exist_ok=True)
    for tool, text in {"docker": NEVER_READY, **tools}.items():
        (bin_dir / tool).write_text(text)
        (bin_dir / tool).chmod(0o755)
    env = dict(
        os.environ,
        PATH=f"{bin_dir}:{os.environ['PATH']}",
        ISAAC_SIM_CONTAINER="isaac-sim-1",
        ISAAC_SIM_READY_MARKER=str(tmp_path / "instance-1.ready"),
        ISAAC_SIM_READY_TIMEOUT=timeout,
        ISAAC_SIM_READY_PATTERN=pattern,
        **({"MAINPID": str(mainpid)} if mainpid else {}),
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
    looks = tmp_path / "looks"
    done = gate(
        tmp_path,
        r"App is loaded\.",
        timeout="60",
        # a container that prints its ready line from the third look at its logs on
        docker=(
            "#!/bin/sh\n"
            '[ "$1" = inspect ] && { echo running; exit 0; }\n'
            f'echo x >> {looks}; [ "$(wc -l < {looks})" -ge 3 ] && echo "Isaac Sim Full App is loaded."\n'
            "exit 0\n"
        ),
        # the gate's waits, written down (and taken for real)
        sleep=f'#!/bin/sh\necho "$1" >> {tmp_path / "sleeps"}\nexec /bin/sleep "$1"\n',
    )
    assert done.returncode == 0, done.stderr
    assert done.stdout == "isaac-sim-1 is ready\n"
    assert (tmp_path / "sleeps").read_text().split() == ["0.25", "0.25"]
    assert (tmp_path / "instance-1.ready").read_text().strip().isdigit()


def test_a_container_that_ended_leaves_the_unit_s_result_to_the_run_script(tmp_path):
    """The gate gives up only after the run script (the unit's main process) has said how the app
    ended and exited with its status: systemd then takes the script's status for the start's result."""
    # the "script": a process of its own that ends 1.5 s from now (reaped by init, as systemd reaps it)
    pid = subprocess.run(
        ["sh", "-c", "sleep 1.5 >/dev/null 2>&1 & echo $!"], capture_output=True, text=True, check=True
    ).stdout
    started = time.monotonic()
    done = gate(tmp_path, "x", timeout="60", mainpid=int(pid), docker='#!/bin/sh\n[ "$1" = inspect ] && echo exited\n')
    took = time.monotonic() - started
    assert done.returncode == 1 and "isaac-sim-1 stopped before it was ready" in done.stderr
    # it waited for the script to end (1.5 s), not for its own bound of 5 s
    assert 1.4 < took < 5, took
