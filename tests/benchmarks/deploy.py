#!/usr/bin/env python
"""Benchmark: deploy 1 host x 4 instances with the image already on the host.

Prints the cold deploy time, the idempotent re-run time, its ratio to a no-op
play on the same host, and the re-run's changed count (which must be 0); then
where the re-run's time goes: per task file and the slowest tasks (medians over
the re-runs, timed by tools/callback_plugins/task_times.py).
A script, not a test: timings on shared machines are noisy, so it reports
figures instead of asserting them. Run after ./tools/bootstrap:

    .venv/bin/python tests/benchmarks/deploy.py [--runs 3]
"""

from __future__ import annotations

import argparse
import collections
import json
import statistics
import sys

from benchhost import ENV, ROOT, bench_host, timed_play

HOST = "isaacsim-bench-1"

NOOP_PLAY = """- name: No-op play (the baseline)
  hosts: isaac_sim_hosts
  gather_facts: true
  tasks:
    - name: Nothing
      ansible.builtin.ping:
"""


def timed_tasks(inv, playbook, tmp, n):
    """(seconds, changed, [task times]) of one run with the task_times callback."""
    out = tmp / f"tasks-{n}.json"
    env = dict(
        ENV,
        ANSIBLE_CALLBACK_PLUGINS=str(ROOT / "tools" / "callback_plugins"),
        ANSIBLE_CALLBACKS_ENABLED="task_times",
        TASK_TIMES_FILE=str(out),
    )
    seconds, changed = timed_play(inv, playbook, HOST, env=env)
    return seconds, changed, json.loads(out.read_text())


def where(tasks_of_runs):
    """Median seconds per task file and per task over the runs (a task is its place in the run)."""
    per_task = collections.defaultdict(list)
    for tasks in tasks_of_runs:
        for i, t in enumerate(tasks):
            per_task[(i, t["task"], t["path"].rsplit(":", 1)[0], t["status"])].append(t.get("seconds", 0.0))
    rows = [(key, statistics.median(times)) for key, times in per_task.items()]
    per_file = collections.defaultdict(float)
    for (_i, _name, path, _status), seconds in rows:
        per_file[path.split("/isaacsim/fleet/")[-1].replace(str(ROOT) + "/", "") or "(play start)"] += seconds
    return rows, per_file


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=3, help="re-runs and no-op plays to take the median of")
    parser.add_argument("--all", action="store_true", help="print every task of the re-run, in order")
    args = parser.parse_args()

    with bench_host(HOST) as (inv, tmp):
        noop = tmp / "noop.yml"
        noop.write_text(NOOP_PLAY)
        deploy = ROOT / "playbooks" / "deploy.yml"
        cold, cold_changed = timed_play(inv, deploy, HOST)
        reruns = [timed_tasks(inv, deploy, tmp, n) for n in range(args.runs)]
        noops = [timed_play(inv, noop, HOST)[0] for _n in range(args.runs)]

    rerun = statistics.median(t for t, _c, _tasks in reruns)
    base = statistics.median(noops)
    changed = max(c for _t, c, _tasks in reruns)
    print("deploy benchmark: 1 host x 4 instances, stand-in image already on the host")
    print(f"cold deploy:           {cold:7.1f} s  ({cold_changed} changed)")
    print(f"idempotent re-run:     {rerun:7.1f} s  (median of {args.runs})")
    print(f"no-op play (baseline): {base:7.1f} s  (median of {args.runs}; facts + one ping)")
    print(f"re-run / no-op:        {rerun / base:7.2f} x")
    print(f"re-run changed count:  {changed:7d}    (must be 0)")
    rows, per_file = where([tasks for _t, _c, tasks in reruns])
    ran = sum(1 for (_i, _n, _p, status), _s in rows if status != "skipped")
    print(f"\nwhere the re-run goes: {len(rows)} tasks, {ran} ran, {len(rows) - ran} skipped (medians, s)")
    for path, seconds in sorted(per_file.items(), key=lambda kv: -kv[1]):
        print(f"  {seconds:6.2f}  {path}")
    print("slowest tasks:")
    for (_i, name, _path, status), seconds in sorted(rows, key=lambda r: -r[1])[:12]:
        print(f"  {seconds:6.2f}  {name} ({status})")
    if args.all:
        print("every task, in order:")
        for (_i, name, path, status), seconds in rows:
            print(f"  {seconds:6.2f}  {status:8} {name}  [{path.split('/isaacsim/fleet/')[-1]}]")
    return 0 if changed == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
