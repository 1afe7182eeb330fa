#!/usr/bin/env python3
"""Benchmark: deploy 1 host x 4 instances with the image already on the host.

Prints the cold deploy time, the idempotent re-run time, its ratio to a no-op
play on the same host, and the re-run's changed count (which must be 0).
A script, not a test: timings on shared machines are noisy, so it reports
figures instead of asserting them. Run after ./tools/bootstrap:

    .venv/bin/python tests/benchmarks/deploy.py [--runs 3]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
HOST = "isaacsim-bench-1"
HOSTS = json.dumps({"testbed_hosts": [HOST]})
ENV = dict(os.environ, ANSIBLE_NOCOLOR="1", PATH=f"{ROOT}/.venv/bin:{os.environ['PATH']}")

NOOP_PLAY = """- name: No-op play (the baseline)
  hosts: isaac_sim_hosts
  gather_facts: true
  tasks:
    - name: Nothing
      ansible.builtin.ping:
"""


# the group_vars find the key relative to playbooks/; this playbook lives elsewhere
KEY = (ROOT / "tests" / "fixtures" / "registry" / "ngc-api-key").read_text().strip()
KEY_VAR = ["-e", json.dumps({"isaac_sim_registry_password": KEY})]


def run(cmd, **kw):
    return subprocess.run(cmd, cwd=ROOT, env=ENV, text=True, capture_output=True, **kw)


def timed_play(inventory, playbook, extra=()):
    start = time.monotonic()
    proc = run(["ansible-playbook", "-i", inventory, *extra, playbook])
    elapsed = time.monotonic() - start
    if proc.returncode != 0:
        sys.exit(f"{playbook} failed:\n{proc.stdout[-3000:]}{proc.stderr}")
    changed = int(re.search(rf"{HOST}\s*:.*changed=(\d+)", proc.stdout).group(1))
    return elapsed, changed


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3, help="re-runs and no-op plays to take the median of")
    args = parser.parse_args()

    with tempfile.TemporaryDirectory() as tmp:
        inv = Path(tmp) / "inventory"
        inv.mkdir()
        (inv / "hosts.yml").write_text(
            f"all:\n  children:\n    isaac_sim_hosts:\n      hosts:\n        {HOST}:\n"
            "      vars:\n        ansible_connection: community.docker.docker\n"
        )
        (inv / "group_vars").symlink_to(ROOT / "inventory" / "demo" / "group_vars")
        noop = Path(tmp) / "noop.yml"
        noop.write_text(NOOP_PLAY)

        run(["ansible-playbook", "molecule/resources/destroy.yml", "-e", HOSTS])
        run(["ansible-playbook", "molecule/resources/create.yml", "-e", HOSTS], check=True)
        try:
            # the host gets Docker and the image first: "image already loaded"
            prep = ROOT / "tests" / "benchmarks" / "prepare_host.yml"
            proc = run(["ansible-playbook", "-i", str(inv), *KEY_VAR, str(prep)])
            if proc.returncode != 0:
                sys.exit(f"preparing the host failed:\n{proc.stdout[-3000:]}{proc.stderr}")

            deploy = str(ROOT / "playbooks" / "deploy.yml")
            cold, cold_changed = timed_play(str(inv), deploy)
            reruns = [timed_play(str(inv), deploy) for _ in range(args.runs)]
            noops = [timed_play(str(inv), str(noop))[0] for _ in range(args.runs)]
        finally:
            run(["ansible-playbook", "molecule/resources/destroy.yml", "-e", HOSTS])

    rerun = statistics.median(t for t, _ in reruns)
    base = statistics.median(noops)
    changed = max(c for _, c in reruns)
    print("deploy benchmark: 1 host x 4 instances, stand-in image already on the host")
    print(f"cold deploy:           {cold:7.1f} s  ({cold_changed} changed)")
    print(f"idempotent re-run:     {rerun:7.1f} s  (median of {args.runs})")
    print(f"no-op play (baseline): {base:7.1f} s  (median of {args.runs}; facts + one ping)")
    print(f"re-run / no-op:        {rerun / base:7.2f} x")
    print(f"re-run changed count:  {changed:7d}    (must be 0)")
    return 0 if changed == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
