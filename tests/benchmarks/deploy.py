#!/usr/bin/env python
"""Benchmark: deploy 1 host x 4 instances with the image already on the host.

Prints the cold deploy time, the idempotent re-run time, its ratio to a no-op
play on the same host, and the re-run's changed count (which must be 0).
A script, not a test: timings on shared machines are noisy, so it reports
figures instead of asserting them. Run after ./tools/bootstrap:

    .venv/bin/python tests/benchmarks/deploy.py [--runs 3]
"""

from __future__ import annotations

import argparse
import statistics
import sys

from benchhost import ROOT, bench_host, timed_play

HOST = "isaacsim-bench-1"

NOOP_PLAY = """- name: No-op play (the baseline)
  hosts: isaac_sim_hosts
  gather_facts: true
  tasks:
    - name: Nothing
      ansible.builtin.ping:
"""


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3, help="re-runs and no-op plays to take the median of")
    args = parser.parse_args()

    with bench_host(HOST) as (inv, tmp):
        noop = tmp / "noop.yml"
        noop.write_text(NOOP_PLAY)
        deploy = ROOT / "playbooks" / "deploy.yml"
        cold, cold_changed = timed_play(inv, deploy, HOST)
        reruns = [timed_play(inv, deploy, HOST) for _n in range(args.runs)]
        noops = [timed_play(inv, noop, HOST)[0] for _n in range(args.runs)]

    rerun = statistics.median(t for t, _value in reruns)
    base = statistics.median(noops)
    changed = max(c for _key, c in reruns)
    print("deploy benchmark: 1 host x 4 instances, stand-in image already on the host")
    print(f"cold deploy:           {cold:7.1f} s  ({cold_changed} changed)")
    print(f"idempotent re-run:     {rerun:7.1f} s  (median of {args.runs})")
    print(f"no-op play (baseline): {base:7.1f} s  (median of {args.runs}; facts + one ping)")
    print(f"re-run / no-op:        {rerun / base:7.2f} x")
    print(f"re-run changed count:  {changed:7d}    (must be 0)")
    return 0 if changed == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
