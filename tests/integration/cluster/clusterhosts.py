"""The cluster scenario's hosts (molecule/cluster), driven from outside: commands in a host and
playbooks as an operator runs them."""

from __future__ import annotations

import json
import os
import re
import subprocess

import testbed
from testbed import ROOT, client

CONTROLLER = "slurm-ctl"
# stand-in GPUs per compute node (molecule/cluster/prepare.yml)
NODES = {"slurm-node-1": 2, "slurm-node-2": 1}
MANAGED = "# Ansible managed"
PLAIN = dict(os.environ, ANSIBLE_FORCE_COLOR="0", ANSIBLE_NOCOLOR="1")


def sh(host: str, command: str, check: bool = True) -> str:
    """A shell command in a test host: its output (stdout and stderr together)."""
    code, out = client().containers.get(host).exec_run(["sh", "-c", command])
    text = out.decode()
    if check and code != 0:
        raise AssertionError(f"{command!r} on {host} failed ({code}): {text}")
    return text


def squash(text: str) -> str:
    """Output with every run of whitespace made one space: Ansible wraps long messages."""
    return re.sub(r"\s+", " ", text)


def playbook_command(name: str, extra: dict | None = None) -> list:
    """The command line of a playbook of the collection on the cluster's inventory."""
    cmd = ["ansible-playbook", "-i", testbed.inventory(), str(ROOT / "playbooks" / name)]
    if extra:
        cmd += ["-e", json.dumps(extra)]
    return cmd


def playbook(name: str, extra: dict | None = None, timeout: int = 600) -> subprocess.CompletedProcess:
    """A playbook of the collection on the cluster's inventory, as an operator runs it."""
    cmd = playbook_command(name, extra)
    return subprocess.run(cmd, capture_output=True, text=True, env=PLAIN, cwd=ROOT, timeout=timeout, check=False)
