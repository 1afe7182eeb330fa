"""isaac-sim-orphans, an ExecStartPre of every instance and companion, run by the machine's Python with
stand-ins for ctr and docker on the script's own paths: containerd's tasks in Docker's namespace, which
of them Docker knows, and each one's OCI spec are the test's; what is cleared is the script's."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

FILES = Path(__file__).resolve().parents[4] / "roles" / "isaac_sim" / "files"
LOST_OURS, LOST_CACHE, LOST_OTHER, KNOWN = ("a" * 64, "b" * 64, "c" * 64, "d" * 64)
CACHE = "/var/lib/isaac-sim/instance-1/cache/main"


@pytest.fixture
def orphans(tmp_path):
    """orphans(docker_answers=True) -> (exit status, output, ctr calls)."""
    state = tmp_path / "state"
    state.mkdir()
    specs = {
        LOST_OURS: {"process": {"env": ["PATH=/bin", "ISAAC_SIM_INSTANCE=3"]}, "mounts": []},
        LOST_CACHE: {"process": {"env": []}, "mounts": [{"source": CACHE, "destination": "/isaac-sim/.cache"}]},
        LOST_OTHER: {"process": {"env": ["ISAAC_SIM=1"]}, "mounts": [{"source": "/srv/db"}]},
        KNOWN: {"process": {"env": ["ISAAC_SIM_INSTANCE=0"]}, "mounts": []},
    }
    for task, spec in specs.items():
        (state / task).write_text(json.dumps({"Spec": spec}))
    calls = tmp_path / "ctr.calls"
    ctr = tmp_path / "ctr"
    ctr.write_text(
        "#!/bin/sh\n"
        f'echo "$*" >> {calls}\n'
        "shift 2\n"
        f'case "$1 $2" in\n'
        f'  "tasks ls") ls {state} ;;\n'
        f'  "containers info") cat {state}/"$3" ;;\n'
        f'  "tasks kill") rm -f {state}/"$5" ;;\n'
        f'  "tasks delete") [ ! -e {state}/"$3" ] || exit 1 ;;\n'
        "esac\nexit 0\n"
    )
    docker = tmp_path / "docker"
    docker.write_text(f'#!/bin/sh\n[ "$1" = ps ] && [ "$DOCKER_DOWN" = 0 ] && echo {KNOWN} && exit 0\nexit 1\n')
    for f in (ctr, docker):
        f.chmod(0o755)
    script = tmp_path / "isaac-sim-orphans"
    text = (FILES / "isaac-sim-orphans").read_text()
    script.write_text(text.replace('"/usr/bin/docker"', repr(str(docker))).replace('"/usr/bin/ctr"', repr(str(ctr))))

    def go(docker_answers=True):
        env = dict(
            os.environ,
            ISAAC_SIM_CONTAINER="isaac-sim-1",
            ISAAC_SIM_CACHES=shlex.join([CACHE, "/var/lib/isaac-sim/instance-1/cache/kit"]),
            DOCKER_DOWN="0" if docker_answers else "1",
        )
        done = subprocess.run(
            [sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=60, check=False
        )
        said = calls.read_text().splitlines() if calls.exists() else []
        return done.returncode, done.stdout + done.stderr, said

    return go


def test_only_our_containers_docker_lost_are_cleared_and_said(orphans):
    rc, out, calls = orphans()
    assert rc == 0
    killed = sorted(c.split()[-1] for c in calls if " tasks kill " in c)
    assert killed == sorted([LOST_OURS, LOST_CACHE])
    removed = sorted(c.split()[-1] for c in calls if " containers delete " in c)
    assert removed == killed
    # a lost task that is not ours (no mark, not this instance's caches) and one Docker knows: untouched
    assert not any(LOST_OTHER in c or KNOWN in c for c in calls if " kill " in c or " delete " in c)
    assert out.count("was stopped and removed") == 2
    assert "isaac-sim-1: a container of this collection that containerd still ran and Docker no longer knew" in out


def test_nothing_is_touched_while_docker_does_not_answer(orphans):
    # Docker restarting: what it does not know yet may be about to be restored
    rc, out, calls = orphans(docker_answers=False)
    assert rc == 0 and out == "" and not [c for c in calls if " kill " in c or " delete " in c or " info " in c]
