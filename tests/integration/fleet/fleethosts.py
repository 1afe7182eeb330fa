"""The fleet scenario's three hosts, driven from outside: playbooks as an operator runs them,
commands inside a host, and what each host's instances are doing."""

from __future__ import annotations

import functools
import json
import os
import re
import subprocess
from pathlib import Path

import testbed
from testbed import ROOT, client

INSTANCES = 4
SIGNAL = 49100


@functools.cache
def _hosts() -> tuple:
    out = subprocess.run(
        ["ansible-inventory", "-i", testbed.inventory(), "--list"], capture_output=True, text=True, check=True, cwd=ROOT
    )
    return tuple(sorted(json.loads(out.stdout)["isaac_sim_hosts"]["hosts"]))


def hosts() -> list:
    """The fleet's hosts, sorted. Read once per test session: the inventory does not change during one,
    and each ansible-inventory call is an Ansible start-up, seconds on a slow machine."""
    return list(_hosts())


def sh(host: str, command: str) -> str:
    code, out = client().containers.get(host).exec_run(["sh", "-c", command])
    if code != 0:
        raise AssertionError(f"{command!r} on {host} failed ({code}): {out.decode()}")
    return out.decode()


def ip(host: str) -> str:
    return client().containers.get(host).attrs["NetworkSettings"]["IPAddress"]


def containers(host: str) -> dict:
    """The instances' containers (not their companions'): {name: (id, image)}."""
    out = sh(host, "docker ps --no-trunc --filter name=isaac-sim- --format '{{.Names}} {{.ID}} {{.Image}}'")
    found = (line.split() for line in out.strip().splitlines())
    return {name: (cid, image) for name, cid, image in found if re.fullmatch(r"isaac-sim-\d+", name)}


def ready_fleet(timeout=240) -> list:
    """The fleet's hosts, once every instance of each is ready (the fixture of a test module)."""
    found = hosts()
    for h in found:
        testbed.wait_for(lambda h=h: all_ready(h), timeout=timeout, what=f"{h} ready")
    return found


def all_ready(host: str) -> bool:
    out = sh(host, "systemctl is-active isaac-sim@0 isaac-sim@1 isaac-sim@2 isaac-sim@3; ls /run/isaac-sim")
    return out.count("active\n") == INSTANCES and all(f"instance-{i}.ready" in out for i in range(INSTANCES))


def playbook_argv(name: str, extra: dict | None, limit: str | None) -> list:
    cmd = ["ansible-playbook", "-i", testbed.inventory(), str(ROOT / "playbooks" / name)]
    if extra:
        cmd += ["-e", json.dumps(extra)]
    return cmd + (["--limit", limit] if limit else [])


PLAIN = {"ANSIBLE_FORCE_COLOR": "0", "ANSIBLE_NOCOLOR": "1"}


def squash(text: str) -> str:
    """Output with every run of whitespace made one space: Ansible wraps long messages."""
    return re.sub(r"\s+", " ", text)


def playbook(name: str, extra: dict | None = None, limit: str | None = None) -> subprocess.CompletedProcess:
    """Run unattended: stdin is not a terminal, as under cron or CI."""
    return testbed.timed(
        f"playbook {Path(name).stem}",
        lambda: subprocess.run(
            playbook_argv(name, extra, limit),
            capture_output=True,
            text=True,
            env=dict(os.environ, **PLAIN),
            timeout=1500,
            cwd=ROOT,
            stdin=subprocess.DEVNULL,
            check=False,
        ),
    )


PROBE = r"""
import json, socket, sys, threading
target, wanted = sys.argv[1], json.loads(sys.argv[2])
out = {}

def one(proto, port, path):
    key = f"{proto}/{port}"
    try:
        if proto == "udp":
            s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            s.settimeout(3)
            s.sendto(b"probe", (target, port))
            out[key] = s.recv(200).decode().strip()
            return
        s = socket.create_connection((target, port), timeout=3)
        s.settimeout(3)
        s.sendall(f"GET {path} HTTP/1.0\r\n\r\n".encode() if path else b"hello\r\n")
        out[key] = s.recv(200).decode(errors="replace").splitlines()[0]
    except socket.timeout:
        out[key] = "timeout"
    except OSError as exc:
        out[key] = type(exc).__name__

threads = [threading.Thread(target=one, args=w) for w in wanted]
for t in threads:
    t.start()
for t in threads:
    t.join()
print(json.dumps(out))
"""


def probe(from_host: str, target: str, wanted: list) -> dict:
    """{"tcp/49100": first line of the answer, or "timeout"} for [(proto, port, http path or "")],
    every port probed at once from from_host (a dropped one costs its timeout, once)."""
    script = PROBE.replace("'", "'\\''")
    arg = json.dumps(wanted)
    return json.loads(sh(from_host, f"python3 -c '{script}' {target} '{arg}'"))
