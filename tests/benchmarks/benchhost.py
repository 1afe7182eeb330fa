"""A throw-away benchmark host: a molecule-style systemd container with Docker and the stand-in image.

Shared by the benchmark scripts; not a test.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
ENV = dict(os.environ, ANSIBLE_NOCOLOR="1", PATH=f"{ROOT}/.venv/bin:{os.environ['PATH']}")
# the group_vars find the key relative to playbooks/; the benchmarks' playbooks live elsewhere
KEY = (ROOT / "tests" / "fixtures" / "registry" / "ngc-api-key").read_text().strip()
KEY_VAR = ["-e", json.dumps({"isaac_sim_registry_password": KEY})]


def run(cmd, **kw):
    check = kw.pop("check", False)
    return subprocess.run(cmd, cwd=ROOT, env=kw.pop("env", ENV), text=True, capture_output=True, check=check, **kw)


def timed_play(inventory, playbook, host, extra=(), env=None):
    """(seconds, changed count of host) of one ansible-playbook run; exits on failure."""
    start = time.monotonic()
    proc = run(["ansible-playbook", "-i", str(inventory), *extra, str(playbook)], env=env or ENV)
    elapsed = time.monotonic() - start
    if proc.returncode != 0:
        sys.exit(f"{playbook} failed:\n{proc.stdout[-3000:]}{proc.stderr}")
    return elapsed, int(re.search(rf"{host}\s*:.*changed=(\d+)", proc.stdout).group(1))


@contextlib.contextmanager
def bench_host(name):
    """Yields (inventory dir, tmp dir) for fresh hosts (one name or a list) with Docker and the image.

    The hosts are removed afterwards.
    """
    names = [name] if isinstance(name, str) else list(name)
    hosts = json.dumps({"testbed_hosts": names})
    with tempfile.TemporaryDirectory() as tmp:
        inv = Path(tmp) / "inventory"
        inv.mkdir()
        listed = "".join(f"        {n}:\n" for n in names)
        (inv / "hosts.yml").write_text(
            f"all:\n  children:\n    isaac_sim_hosts:\n      hosts:\n{listed}"
            "      vars:\n        ansible_connection: community.docker.docker\n"
        )
        (inv / "group_vars").symlink_to(ROOT / "inventory" / "demo" / "group_vars")
        run(["ansible-playbook", "molecule/resources/destroy.yml", "-e", hosts])
        run(["ansible-playbook", "molecule/resources/create.yml", "-e", hosts], check=True)
        try:
            prep = ROOT / "tests" / "benchmarks" / "prepare_host.yml"
            proc = run(["ansible-playbook", "-i", str(inv), *KEY_VAR, str(prep)])
            if proc.returncode != 0:
                sys.exit(f"preparing the host failed:\n{proc.stdout[-3000:]}{proc.stderr}")
            yield inv, Path(tmp)
        finally:
            run(["ansible-playbook", "molecule/resources/destroy.yml", "-e", hosts])
