"""Helpers for tests on the molecule test hosts (systemd + Docker inside a container)."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import time
from pathlib import Path

import docker

ROOT = Path(__file__).resolve().parents[2]
CONVERGE = ROOT / "molecule" / "resources" / "converge.yml"
INSTANCES = 4


def client():
    return docker.from_env()


def sh(host_name: str, command: str, check=True) -> subprocess.CompletedProcess:
    """Run a shell command inside a test host."""
    proc = subprocess.run(
        ["docker", "exec", host_name, "sh", "-c", command], capture_output=True, text=True, timeout=300
    )
    if check and proc.returncode != 0:
        raise AssertionError(f"{command!r} on {host_name} failed ({proc.returncode}): {proc.stdout}{proc.stderr}")
    return proc


def host_ip(host_name: str) -> str:
    return client().containers.get(host_name).attrs["NetworkSettings"]["IPAddress"]


def inventory() -> str:
    inv = os.environ.get("MOLECULE_INVENTORY_FILE")
    if not inv:
        raise RuntimeError("run these tests through molecule (molecule verify), which provides the inventory")
    return inv


def run_playbook(host_name: str, extra_vars: dict | None = None, check=False) -> subprocess.CompletedProcess:
    cmd = ["ansible-playbook", "-i", inventory(), "--limit", host_name, str(CONVERGE)]
    if extra_vars:
        cmd += ["-e", json.dumps(extra_vars)]
    if check:
        cmd.append("--check")
    env = dict(os.environ, ANSIBLE_FORCE_COLOR="0", ANSIBLE_NOCOLOR="1")
    return subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=900, cwd=ROOT)


def unit_show(host_name: str, unit: str) -> dict:
    out = sh(host_name, f"systemctl show {shlex.quote(unit)} -p ActiveState,SubState,NRestarts,UnitFileState").stdout
    return dict(line.split("=", 1) for line in out.strip().splitlines())


def container_id(host_name: str, name: str) -> str:
    return sh(host_name, f"docker ps -q --no-trunc --filter name=^{name}$").stdout.strip()


def wait_for(predicate, timeout=120, interval=1.0, what="condition"):
    deadline = time.monotonic() + timeout
    last = None
    while time.monotonic() < deadline:
        try:
            last = predicate()
            if last:
                return last
        except Exception as exc:  # noqa: BLE001 - keep polling through restarts
            last = exc
        time.sleep(interval)
    raise AssertionError(f"timed out after {timeout} s waiting for {what} (last: {last!r})")


def instance_ready(host_name: str, i: int) -> bool:
    show = unit_show(host_name, f"isaac-sim@{i}.service")
    marker = sh(host_name, f"test -f /run/isaac-sim/instance-{i}.ready", check=False).returncode == 0
    return show["ActiveState"] == "active" and marker


def all_ready(host_name: str, ids=range(INSTANCES), timeout=180):
    for i in ids:
        wait_for(lambda i=i: instance_ready(host_name, i), timeout=timeout, what=f"isaac-sim@{i} ready")


def snapshot(host_name: str) -> str:
    """Everything our code could change on a host, as one text to compare."""
    return sh(
        host_name,
        "sha256sum /etc/isaac-sim/* /etc/systemd/system/isaac-sim* /etc/docker/daemon.json "
        "/usr/local/libexec/isaac-sim/* 2>/dev/null; "
        "ls -lnR /var/lib/isaac-sim 2>/dev/null | grep -v standin-shader-cache; "
        "docker ps -a --no-trunc --format '{{.ID}} {{.Names}} {{.Status}}' | sed 's/Up .*/Up/'; "
        "systemctl list-units --all --no-legend 'isaac-sim*' | awk '{print $1, $3, $4}'",
        check=False,
    ).stdout
