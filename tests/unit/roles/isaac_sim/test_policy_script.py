"""isaac-sim-policy, isaac-sim-run's check of the container Docker created, run by the machine's
Python beside the host library's files as the lifecycle installs them. Docker is a stand-in on
the script's own path that answers `inspect` with what a test says Docker made; the judging is
the real container policy's."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[4]
FILES = ROOT / "roles" / "isaac_sim" / "files"
HOSTLIB = ROOT / "plugins" / "module_utils" / "hostlib"
PLANNED = ["--network=host", "--user=1234:1234", "--security-opt=no-new-privileges"]


@pytest.fixture
def check(tmp_path):
    """check(planned args, inspected HostConfig, volumes={name: options}, user) -> (exit status, output)."""
    libexec = tmp_path / "libexec"
    libexec.mkdir()
    for name in ("docker_cli.py", "container_policy.py"):
        (libexec / name).write_text((HOSTLIB / name).read_text())
    docker = tmp_path / "docker"
    docker.write_text(
        "#!/bin/sh\n"
        '[ "$1 $2" = "container inspect" ] && { [ -f "$INSPECTED" ] && cat "$INSPECTED" && exit 0; '
        'echo "Error: No such container: $3" >&2; exit 1; }\n'
        '[ "$1 $2" = "volume inspect" ] && cat "$VOLUMES" && exit 0\n'
        "exit 2\n"
    )
    docker.chmod(0o755)
    script = libexec / "isaac-sim-policy"
    script.write_text((FILES / "isaac-sim-policy").read_text().replace('"/usr/bin/docker"', repr(str(docker))))

    def go(planned, host_config, volumes=None, user="1234:1234", exists=True):
        inspected = tmp_path / "inspected.json"
        inspected.unlink(missing_ok=True)
        if exists:
            mounts = [{"Type": "volume", "Name": n} for n in volumes or {}]
            inspected.write_text(
                json.dumps(
                    [{"Name": "/isaac-sim-0", "Config": {"User": user}, "HostConfig": host_config, "Mounts": mounts}]
                )
            )
        (tmp_path / "volumes.json").write_text(
            json.dumps([{"Name": n, "Options": o} for n, o in (volumes or {}).items()])
        )
        env = dict(
            os.environ,
            ISAAC_SIM_CONTAINER="isaac-sim-0",
            ISAAC_SIM_DOCKER_ARGS=shlex.join(planned),
            INSPECTED=str(inspected),
            VOLUMES=str(tmp_path / "volumes.json"),
        )
        done = subprocess.run(
            [sys.executable, str(script)], capture_output=True, text=True, env=env, timeout=30, check=False
        )
        return done.returncode, done.stdout + done.stderr

    return go


def test_a_container_as_its_plan_gave_it_may_start(check, tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    planned = [*PLANNED, f"--volume={data}/cache:/c:rw", "--cap-add=SYS_PTRACE"]
    host = {"Binds": [f"{data}/cache:/c:rw"], "SecurityOpt": ["no-new-privileges"], "CapAdd": ["CAP_SYS_PTRACE"]}
    # the daemon's default cgroup namespace on cgroup v1 hosts, shown though nobody asked for it
    host["CgroupnsMode"] = "host"
    assert check(planned, host) == (0, "")


def test_a_named_volume_made_with_bind_options_is_refused(check):
    rc, out = check(
        [*PLANNED, "-v", "hostetc:/h"],
        {"Binds": ["hostetc:/h"], "SecurityOpt": ["no-new-privileges"]},
        volumes={"hostetc": {"type": "none", "o": "bind", "device": "/etc"}},
    )
    assert rc == 1
    assert out.startswith(
        "isaac-sim-0 was not started: the container policy refuses what Docker made of its arguments: "
        "--volume=hostetc:/h binds (a local volume's options) host path /etc into it"
    )


def test_a_bind_through_a_symbolic_link_is_judged_where_it_leads(check, tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    (data / "maps").symlink_to("/etc")
    planned = [*PLANNED, f"--volume={data}/maps:/maps:ro"]
    rc, out = check(planned, {"Binds": [f"{data}/maps:/maps:ro"], "SecurityOpt": ["no-new-privileges"]})
    assert rc == 1 and "host path /etc into it: the host's configuration" in out


def test_what_docker_made_other_than_the_plan_read_it_is_refused(check):
    # the plan read the arguments as no-new-privileges on and the release's user; Docker says otherwise
    rc, out = check(PLANNED, {"SecurityOpt": ["no-new-privileges", "no-new-privileges=false"]}, user="0")
    assert rc == 1
    assert "--security-opt=no-new-privileges=false lets the container's processes gain privileges" in out
    assert "--user=0 runs the container as root" in out


def test_a_container_docker_cannot_show_is_refused(check):
    rc, out = check(PLANNED, {}, exists=False)
    # not started (fails closed), but as a start that failed and is retried, not as a refusal
    assert rc == 2 and "could not judge the container Docker made" in out and "No such container" in out
