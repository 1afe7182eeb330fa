#!/usr/bin/env python
"""Benchmark: a fleet-wide rolling restart of H = 3 and H = 6 hosts x 4 instances.

Prints, for each H:
  - the total rolling-restart time (the whole playbook: preflight, batches, summary);
  - the physical limit: the sum over batches of the slowest host's measured
    stop + start + ready time of its instances, one after another (the times
    the rollout module measured around each `systemctl restart`);
  - the overhead as a percentage of that limit (goal: at most 15 %);
  - the fewest instances seen answering per host (a watcher probes every port four times a second).

The default serial [1, "25%"] and no soak (the issue's limit counts no soak).
--ready-delay makes the stand-in take that many seconds to get ready, closer to a
real Isaac Sim start. A script, not a test. Run after ./tools/bootstrap:

    .venv/bin/python tests/benchmarks/rollout.py [--hosts 3 6] [--ready-delay 0]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

from benchhost import ENV, ROOT, bench_host, run, timed_play

sys.path.insert(0, str(ROOT / "tests" / "integration"))
from portwatch import Watcher  # noqa: E402

INSTANCES = 4
SIGNAL = 49100


def batches(hosts, serial=(1, 0.25)):
    """Ansible's serial batches: 1 host, then a quarter of the hosts (at least one), repeated."""
    out, rest, sizes = [], list(hosts), list(serial)
    while rest:
        size = sizes.pop(0) if len(sizes) > 1 else sizes[0]
        n = max(1, int(size * len(hosts))) if isinstance(size, float) else size
        out.append(rest[:n])
        rest = rest[n:]
    return out


def restart_times(stdout: str) -> dict:
    """{host: [restart_s per instance]} from the JSON callback's rollout task results."""
    times = {}
    for play in json.loads(stdout)["plays"]:
        for task in play["tasks"]:
            # a role task is named "ROLE : NAME"
            if not task["task"]["name"].endswith(
                ("Apply the plan to the instances", "Restart each instance as it is, ready and soaked before the next")
            ):
                continue
            for host, res in task["hosts"].items():
                times[host] = [d["restart_s"] for d in res.get("done", [])]
    return times


def measure(h: int, ready_delay: int) -> dict:
    names = [f"isaacsim-bench-{i + 1}" for i in range(h)]
    with bench_host(names) as (inv, _tmp):
        extra = {"isaac_sim_env": {"STANDIN_READY_DELAY": str(ready_delay)}} if ready_delay else {}
        timed_play(inv, ROOT / "playbooks" / "deploy.yml", names[0], ["-e", json.dumps(extra)] if extra else [])
        addresses = {
            n: subprocess.run(
                ["docker", "inspect", "-f", "{{.NetworkSettings.IPAddress}}", n],
                capture_output=True,
                text=True,
                check=True,
            ).stdout.strip()
            for n in names
        }
        watcher = Watcher(addresses, [SIGNAL + i for i in range(INSTANCES)])
        watcher.start()
        start = time.monotonic()
        vars_ = {"isaac_sim_rollout_soak": 0, **extra}
        proc = run(
            [
                "ansible-playbook",
                "-i",
                str(inv),
                "-e",
                json.dumps(vars_),
                str(ROOT / "playbooks" / "rolling_restart.yml"),
            ],
            env=dict(ENV, ANSIBLE_STDOUT_CALLBACK="json"),
        )
        total = time.monotonic() - start
        watcher.stop()
        if proc.returncode != 0:
            sys.exit(f"the rolling restart failed:\n{proc.stdout[-3000:]}{proc.stderr}")
        times = restart_times(proc.stdout)
    limit = sum(max(sum(times[n]) for n in batch) for batch in batches(names))
    return {
        "hosts": h,
        "total": total,
        "limit": limit,
        "overhead": 100 * (total - limit) / limit,
        "lowest": min(watcher.lowest().values()),
        "batches": [len(b) for b in batches(names)],
        "per_instance": sum(sum(v) for v in times.values()) / (h * INSTANCES),
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--hosts", type=int, nargs="+", default=[3, 6])
    parser.add_argument("--ready-delay", type=int, default=0, help="stand-in start-up seconds (0: its default, 1-3 s)")
    args = parser.parse_args()
    rows = [measure(h, args.ready_delay) for h in args.hosts]
    print(f"rolling-restart benchmark: {INSTANCES} instances per host, serial [1, 25%], no soak")
    print(
        f"{'H':>2}  {'batches':<20} {'restart/instance':>16} {'total':>8} {'limit':>8} {'overhead':>9}"
        f" {'min up/host':>12}"
    )
    for r in rows:
        print(
            f"{r['hosts']:>2}  {str(r['batches']):<20} {r['per_instance']:15.1f}s {r['total']:7.1f}s {r['limit']:7.1f}s"
            f" {r['overhead']:8.1f}% {r['lowest']:>8}/{INSTANCES}"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
