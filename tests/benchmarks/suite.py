#!/usr/bin/env python
"""Benchmark: a suite of 12 short experiences over H = 3 hosts, P = 2 runs at once per host.

Prints the suite's wall time (the whole test_suite.yml run: planning, the runs, fetching the
artefacts, the report) against the physical limit: the sum of the runs' own durations on their
hosts (each run's set-up, run and tear-down, measured by the host) divided by the H x P slots.
The ratio is wall / limit (1.0 would be a perfect packing with no overhead). A script, not a
test. Run after ./tools/bootstrap:

    .venv/bin/python tests/benchmarks/suite.py [--hosts 3] [--parallel 2]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import yaml
from benchhost import ROOT, bench_host, run, timed_play

FIXTURES = ROOT / "tests" / "fixtures" / "experiences"


def suite_spec(image: str) -> dict:
    return {
        "environment": {"IMAGE": image},
        "timeout": 120,
        "experiences": [
            {"file": str(FIXTURES / "pass.yml"), "repeat": 4},
            {"file": str(FIXTURES / "fail.yml"), "repeat": 2},
            {
                "file": str(FIXTURES / "crash.yml"),
                "parameters": [{"CRASH_RESTART": "no"}, {"CRASH_RESTART": "on-failure"}],
            },
            {"file": str(FIXTURES / "late.yml"), "repeat": 2},
            {"file": str(FIXTURES / "sim.yml"), "repeat": 2},
        ],
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    parser.add_argument("--hosts", type=int, default=3)
    parser.add_argument("--parallel", type=int, default=2)
    args = parser.parse_args()
    names = [f"isaacsim-bench-{i + 1}" for i in range(args.hosts)]
    with bench_host(names) as (inv, _tmp), tempfile.TemporaryDirectory() as out:
        timed_play(inv, ROOT / "playbooks" / "deploy.yml", names[0])
        env = run(["docker", "exec", names[0], "cat", "/etc/isaac-sim/instance-0.env"]).stdout
        image = next(x for x in env.splitlines() if x.startswith("ISAAC_SIM_IMAGE=")).split("=", 1)[1].strip('"')
        spec = Path(out) / "suite.yml"
        spec.write_text(yaml.safe_dump(suite_spec(image)))
        extra = {
            "test_suite_file": str(spec),
            "test_suite_dir": f"{out}/runs",
            "test_suite_parallel_per_host": args.parallel,
        }
        start = time.monotonic()
        proc = run(
            ["ansible-playbook", "-i", str(inv), "-e", json.dumps(extra), str(ROOT / "playbooks" / "test_suite.yml")]
        )
        wall = time.monotonic() - start
        report = Path(out) / "runs" / "suite.json"
        if not report.exists():
            sys.exit(f"the suite did not run:\n{proc.stdout[-3000:]}{proc.stderr}")
        results = json.loads(report.read_text())["results"]
    own = sum(r.get("elapsed", 0) for r in results)
    slots = args.hosts * args.parallel
    limit = own / slots
    verdicts = {}
    for r in results:
        word = (r.get("verdict") or {}).get("result", "error")
        verdicts[word] = verdicts.get(word, 0) + 1
    counts = ", ".join(f"{n} {k}" for k, n in sorted(verdicts.items()))
    print(f"runs: {len(results)} ({counts}) on {args.hosts} hosts x {args.parallel}")
    print(f"sum of the runs' own durations: {own:.1f} s")
    print(f"physical limit (sum / {slots} slots): {limit:.1f} s")
    print(f"suite wall time: {wall:.1f} s")
    print(f"ratio wall / limit: {wall / limit:.2f}x")


if __name__ == "__main__":
    main()
