"""isaac-sim-run, the instances' ExecStart, run by a real bash: how the end of the app is told
to systemd. Docker and systemctl are small recording stand-ins on the script's own paths; the
logic under test is the script's, unchanged."""

from __future__ import annotations

import os
import subprocess
from pathlib import Path

import pytest

FILES = Path(__file__).resolve().parents[4] / "roles" / "isaac_sim" / "files"


@pytest.fixture
def run(tmp_path):
    """run(app_status, ready) -> (exit status, output, systemctl calls)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    calls = tmp_path / "systemctl.calls"
    docker_calls = tmp_path / "docker.calls"
    (bin_dir / "docker").write_text(
        f'#!/bin/sh\necho "$1" >>{docker_calls}\n'
        '[ "$1" = create ] && exit "$CREATE_STATUS"\n[ "$1" = start ] && exit "$APP_STATUS"\nexit 0\n'
    )
    # the journal's stream: what the script tags isaac-sim-events, printed with its tag
    (bin_dir / "systemd-cat").write_text('#!/bin/sh\nsed "s/^/[$2] /"\n')
    (bin_dir / "systemctl").write_text(
        f'#!/bin/sh\necho "$*" >>{calls}\n'
        'case "$*" in *"docker.service"*) [ "$1" = show ] && echo "$DOCKER_STATE"; '
        '[ "$1" = list-jobs ] && echo "$DOCKER_JOB"; exit 0 ;; esac\n'
        '[ "$1" = show ] && echo active\nexit 0\n'
    )
    # the script as installed, with Docker at the stand-in's path
    script = tmp_path / "isaac-sim-run"
    script.write_text(
        (FILES / "isaac-sim-run")
        .read_text()
        .replace("/usr/bin/docker", str(bin_dir / "docker"))
        .replace("/usr/bin/python3 ", "")
    )
    (tmp_path / "isaac-sim-ports").write_text("#!/bin/sh\nexit 0\n")
    # the container policy's check: its answer is the test's
    (tmp_path / "isaac-sim-policy").write_text(
        '#!/bin/sh\n[ "$POLICY_STATUS" = 0 ] || echo refused\nexit "$POLICY_STATUS"\n'
    )
    for f in (*bin_dir.iterdir(), script, tmp_path / "isaac-sim-ports", tmp_path / "isaac-sim-policy"):
        f.chmod(0o755)
    marker = tmp_path / "instance-2.ready"

    def go(status: int, ready: bool, docker_state="active", docker_job="", create=0, policy=0):
        marker.unlink(missing_ok=True)
        calls.unlink(missing_ok=True)
        docker_calls.unlink(missing_ok=True)
        if ready:
            marker.write_text("1\n")
        env = dict(
            os.environ,
            PATH=f"{bin_dir}:{os.environ['PATH']}",
            APP_STATUS=str(status),
            ISAAC_SIM_CONTAINER="isaac-sim-2",
            ISAAC_SIM_UNIT="isaac-sim@2.service",
            ISAAC_SIM_IMAGE="img",
            ISAAC_SIM_READY_MARKER=str(marker),
            DOCKER_STATE=docker_state,
            DOCKER_JOB=docker_job,
            CREATE_STATUS=str(create),
            POLICY_STATUS=str(policy),
        )
        done = subprocess.run(["bash", str(script)], capture_output=True, text=True, env=env, timeout=30, check=False)
        said = calls.read_text().splitlines() if calls.exists() else []
        go.docker = docker_calls.read_text().split() if docker_calls.exists() else []
        return done.returncode, done.stdout + done.stderr, said

    return go


def test_a_clean_exit_after_ready_is_a_session_end_that_flushes_the_start_limit(run):
    rc, out, calls = run(0, ready=True)
    assert rc == 0
    assert "isaac-sim-2: session ended (the app exited 0 after it was ready)" in out
    assert "[isaac-sim-events] event=session_end container=isaac-sim-2" in out
    assert "reset-failed isaac-sim@2.service" in calls


def test_a_crash_after_ready_stays_counted(run):
    rc, out, calls = run(1, ready=True)
    assert rc == 1
    assert "isaac-sim-2 crashed (exit status 1): counted against the start limit" in out
    assert "[isaac-sim-events] event=crash container=isaac-sim-2" in out
    assert not [c for c in calls if c.startswith("reset-failed")]


def test_a_clean_exit_before_ready_stays_counted(run):
    rc, out, calls = run(0, ready=False)
    assert rc == 0
    assert "exited 0 before it was ready: counted as a failed start" in out
    assert not [c for c in calls if c.startswith("reset-failed")]


@pytest.mark.parametrize(
    "state, job",
    [
        # dockerd killed: systemd restarts it
        ("activating", ""),
        # systemctl stop docker / restart docker: its job waits for the instances to stop first
        ("active", "812 docker.service stop waiting"),
        ("active", "813 docker.service restart waiting"),
    ],
)
def test_docker_going_away_is_no_crash_and_its_restart_is_not_counted(run, state, job):
    rc, out, calls = run(125, ready=True, docker_state=state, docker_job=job)
    assert "isaac-sim-2: Docker went away under it" in out and "not counted as a crash" in out
    assert "reset-failed isaac-sim@2.service" in calls
    # one event for the exit: status counted five crashes for instances that never crashed
    assert out.count("[isaac-sim-events] event=") == 1 and "event=docker_away" in out
    assert "crashed" not in out and rc == 125


def test_no_answer_about_docker_is_no_sign_that_it_went_away(run):
    # systemctl ended by systemd's stop signal prints nothing: the app's own end is still a crash
    rc, out, _calls = run(1, ready=False, docker_state="")
    assert rc == 1 and "Docker went away" not in out and "crashed (exit status 1)" in out


def test_a_crash_while_docker_runs_is_a_crash(run):
    _rc, out, calls = run(1, ready=True, docker_job="900 isaac-sim@2.service restart waiting")
    assert "Docker went away" not in out and not [c for c in calls if c.startswith("reset-failed")]


def test_docker_creates_the_container_the_policy_judges_it_and_only_then_it_starts(run):
    rc, _out, _calls = run(0, ready=True)
    assert rc == 0 and run.docker == ["create", "start"]


def test_a_container_the_policy_refuses_is_removed_never_started_and_not_retried(run):
    rc, out, calls = run(0, ready=True, policy=1)
    assert rc == 77 and "refused" in out
    assert run.docker == ["create", "rm"]
    # no event: nothing ran, nothing crashed
    assert "event=" not in out and not calls


def test_a_container_the_policy_could_not_judge_is_removed_and_its_start_fails_to_be_retried(run):
    rc, _out, calls = run(0, ready=True, policy=2)
    assert rc == 1 and run.docker == ["create", "rm"] and not calls


def test_a_container_docker_could_not_create_ends_as_a_failed_docker_run(run):
    rc, out, _calls = run(0, ready=False, create=125)
    assert rc == 125 and run.docker == ["create"]
    assert "isaac-sim-2 crashed (exit status 125): counted against the start limit" in out
