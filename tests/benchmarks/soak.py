#!/usr/bin/env python
"""Soak: four stand-in 6.x instances deployed with the default scenario's aggressive health
settings (a probe every 2 s, unhealthy after 2 failures, restarted by the host after 8 s) are
watched for --minutes (10 by default); then one is hung and the time until its host restarts
it is measured.

Prints: the samples taken, how many instances were healthy in every sample, the failed health
probes Docker recorded, the restarts by the host during the soak (the target is 0), and for
the hung instance the seconds until unhealthy, restarted and ready again.

A script, not a test: it takes as long as it soaks. Run after ./tools/bootstrap:

    .venv/bin/python tests/benchmarks/soak.py [--minutes 10]
"""

from __future__ import annotations

import argparse
import sys
import time

from benchhost import KEY_VAR, ROOT, bench_host, run

HOST = "isaacsim-soak-1"
INSTANCES = 4
# the default scenario's settings (molecule/default/inventory/hosts.yml)
SETTINGS = [
    "-e",
    "isaac_sim_health_interval=2",
    "-e",
    "isaac_sim_health_retries=2",
    "-e",
    "isaac_sim_unhealthy_restart=8",
    "-e",
    "isaac_sim_web_viewer_image=",
]
LOOK = (
    "for i in 0 1 2 3; do "
    "printf '%s ' $i $(systemctl show -p InvocationID --value isaac-sim@$i) "
    "$(docker inspect -f '{{.State.Health.Status}} {{len .State.Health.Log}} {{.State.Health.FailingStreak}}' "
    "isaac-sim-$i 2>/dev/null || echo none 0 0); echo; done; "
    "for i in 0 1 2 3; do echo $i $(docker inspect -f "
    "'{{range .State.Health.Log}}{{.Start.UnixNano}}:{{.ExitCode}} {{end}}' isaac-sim-$i); done"
)


def look():
    """({id: (invocation, health)}, {(id, probe start) of each failed probe in Docker's health logs})."""
    out = run(["docker", "exec", HOST, "bash", "-c", LOOK]).stdout.splitlines()
    states = {}
    for line in out[:INSTANCES]:
        parts = line.split()
        if len(parts) >= 3:
            states[int(parts[0])] = (parts[1], parts[2])
    failed = set()
    for line in out[INSTANCES:]:
        i, *probes = line.split()
        failed |= {(i, p.split(":")[0]) for p in probes if not p.endswith(":0")}
    return states, failed


def main():
    parser = argparse.ArgumentParser()
    parser.add_argument("--minutes", type=float, default=10)
    args = parser.parse_args()
    with bench_host(HOST) as (inv, _tmp):
        deploy = run(["ansible-playbook", "-i", str(inv), *KEY_VAR, *SETTINGS, str(ROOT / "playbooks" / "deploy.yml")])
        if deploy.returncode != 0:
            sys.exit(f"deploy failed:\n{deploy.stdout[-3000:]}{deploy.stderr}")
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and {h for _i, h in look()[0].values()} != {"healthy"}:
            time.sleep(2)
        first, _failed = look()
        samples, always_healthy, failed_seen = 0, set(range(INSTANCES)), set()
        end = time.monotonic() + args.minutes * 60
        while time.monotonic() < end:
            states, failed = look()
            samples += 1
            failed_seen |= failed
            for i in range(INSTANCES):
                if states.get(i, ("", ""))[1] != "healthy":
                    always_healthy.discard(i)
            time.sleep(5)
        last, _failed = look()
        restarted = [i for i in range(INSTANCES) if last.get(i, ("",))[0] != first.get(i, ("-",))[0]]
        print(f"soak: {args.minutes:g} min, {samples} samples, health probe every 2 s")
        print(f"  healthy in every sample: {len(always_healthy)}/{INSTANCES}")
        # Docker keeps each container's last 5 probes; a 5 s sample sees every 2 s probe
        print(f"  failed health probes: {len(failed_seen)} (of about {int(args.minutes * 60 / 2) * INSTANCES})")
        print(f"  restarted by the host during the soak: {len(restarted)} (target 0) {restarted or ''}")

        # then instance 2 hangs: ports open, nothing accepted
        before = last[2][0]
        run(["docker", "exec", HOST, "docker", "exec", "isaac-sim-2", "touch", "/tmp/standin-hang"])
        start, unhealthy_at, restarted_at, ready_at = time.monotonic(), None, None, None
        while time.monotonic() - start < 180:
            states, _failed = look()
            invocation, health = states.get(2, ("", ""))
            now = time.monotonic() - start
            if unhealthy_at is None and health == "unhealthy":
                unhealthy_at = now
            if restarted_at is None and invocation and invocation != before:
                restarted_at = now
            if restarted_at is not None and health == "healthy":
                ready_at = now
                break
            time.sleep(1)

        def secs(value):
            return "never (180 s)" if value is None else f"{value:.0f} s"

        print("hung instance (isaac-sim-2):")
        print(f"  unhealthy after {secs(unhealthy_at)}, restarted by its host after {secs(restarted_at)}, ")
        print(f"  healthy again after {secs(ready_at)} (settings: 2 failures x 2 s, then 8 s unhealthy)")


if __name__ == "__main__":
    main()
