#!/usr/bin/env python
"""Benchmark: simulator sessions from the pool on a test fleet of 2 hosts x 4 stand-in instances, the
first host also the front door (issue 45, item 9).

Prints:
- the time from a request (POST /api/sessions with a token, through nginx) to its answer naming the
  instance and its entrance (this fleet runs no web viewer, as api.py's: the entrance is then
  null; where viewers run it is the door's fixed address for the instance, in the same answer),
  while a reset instance is free: p50 and p95 over --requests, beside the API's own round
  trip (GET /api/sessions, the median of 20), and their ratio;
- 20 requests at once for 8 free instances: how many were granted and queued, whether the queue's
  places follow the order the requests were taken in, and how many instances were given twice
  (from the fleet's own listing of holders);
- with none free and one person waiting: the time from ending a session to the waiting person's
  session, less the instance's own reset (the give-back action's time on the host, from its agent),
  the median of --waits.

A script, not a test: timings on shared machines are noisy. Run after ./tools/bootstrap:

    .venv/bin/python tests/benchmarks/sessions.py [--requests 50] [--waits 5]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import threading
import time

from api import Door, door_fleet, percentile
from benchhost import bench_host

HOSTS = [f"isaacsim-benchsess-{i}" for i in (1, 2)]
INSTANCES = 4


# when the last call's attempt that the API took began (a figure starts there, not at a refused attempt)
TAKEN = {"at": 0.0}


def call(door: Door, method: str, path: str, body=None) -> tuple:
    """(status, answer); a write over the API's own limit (30 a minute per token) waits its turn and is
    asked again, so each figure is of an attempt the API took (TAKEN: when it began)."""
    for _attempt in range(120):
        TAKEN["at"] = time.monotonic()
        status, data = door.call(method, path, body)
        if status != 429:
            break
        time.sleep(2.1)
    try:
        return status, json.loads(data)
    except ValueError:
        return status, {"raw": data[:300].decode("utf-8", "replace")}


def wait(what: str, check, timeout: float = 180.0, every: float = 0.1):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        got = check()
        if got:
            return got
        time.sleep(every)
    # what the door's API said meanwhile, for whoever reads why
    said = subprocess.run(
        ["docker", "exec", HOSTS[0], "journalctl", "-u", "isaac-sim-front-door-api", "-n", "80", "--no-pager"],
        capture_output=True,
        text=True,
        check=False,
    )
    sys.exit(f"timed out waiting for {what}; the API's journal:\n{said.stdout[-6000:]}")


def active_now(door: Door, url: str):
    s = call(door, "GET", url)[1]
    return s if s.get("state") == "active" else None


def free_count(door: Door) -> int:
    _s, fleet = call(door, "GET", "/api/fleet")
    return sum(1 for h in fleet["hosts"] for i in h["instances"] if i["ready"] and not i["holder"])


def end_all(door: Door) -> None:
    """Every session and place of the bench's user ended, and every instance free and ready again."""
    _s, mine = call(door, "GET", "/api/sessions")
    for s in mine["mine"]:
        call(door, "DELETE", s["url"])
    wait("every session to end", lambda: not call(door, "GET", "/api/sessions")[1]["mine"])
    wait("every instance to be free and ready", lambda: free_count(door) == len(HOSTS) * INSTANCES)


def to_an_entrance(door: Door, requests: int) -> list:
    """Seconds from each POST to its 201 with an entrance, taking the free instances a round at a time."""
    took = []
    while len(took) < requests:
        for _k in range(min(len(HOSTS) * INSTANCES, requests - len(took))):
            time.sleep(2.1)  # within the API's 30 writes a minute per token: no attempt of a figure is refused
            status, s = call(door, "POST", "/api/sessions", {})
            answered = time.monotonic()
            # (this fleet runs no web viewer, as api.py's: the answer names the instance, and the entrance is
            # the door's fixed address for it, read from its configuration in the same answer)
            if status != 201 or "entrance" not in s or s.get("instance") is None:
                sys.exit(f"no session: {status} {s}")
            took.append(answered - TAKEN["at"])
        end_all(door)
    return took


def burst(door: Door, n: int) -> tuple:
    """(granted, queued answers) of n requests at once."""
    answers, lock = [], threading.Lock()

    def ask():
        got = call(door, "POST", "/api/sessions", {})
        with lock:
            answers.append(got)

    threads = [threading.Thread(target=ask) for _k in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    granted = [s for status, s in answers if status == 201]
    queued = [s for status, s in answers if status == 202]
    return granted, queued


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--requests", type=int, default=50)
    parser.add_argument("--waits", type=int, default=5)
    args = parser.parse_args()
    with bench_host(HOSTS) as (inv, tmp):
        # one person asks for all of them here: the per-person rule is not what is measured
        api = door_fleet(inv, tmp, HOSTS, INSTANCES, ["read", "use", "operate"], {"front_door_sim_per_person": 40})
        wait("every instance to be ready behind the door", lambda: free_count(api) == len(HOSTS) * INSTANCES)

        round_trips = []
        for _k in range(20):
            began = time.monotonic()
            call(api, "GET", "/api/sessions")
            round_trips.append(time.monotonic() - began)
        trip = statistics.median(round_trips)
        took = to_an_entrance(api, args.requests)
        p50, p95 = percentile(took, 0.5), percentile(took, 0.95)
        print(
            f"request to an entrance, {len(took)} requests with a free instance: p50 {p50 * 1000:.0f} ms, p95 "
            f"{p95 * 1000:.0f} ms; the API's own round trip {trip * 1000:.0f} ms; p50/round trip {p50 / trip:.1f}x, "
            f"p50 beyond it {(p50 - trip) * 1000:+.0f} ms"
        )

        granted, queued = burst(api, 20)
        places = sorted(queued, key=lambda s: s["created"])
        in_order = [s["place"] for s in places] == list(range(1, len(queued) + 1))
        _s, fleet = call(api, "GET", "/api/fleet")
        holders = [i["holder"]["id"] for h in fleet["hosts"] for i in h["instances"] if i["holder"]]
        twice = len(holders) - len(set(holders)) + len(granted) - len({(s["host"], s["instance"]) for s in granted})
        print(
            f"20 requests at once for {len(HOSTS) * INSTANCES} free instances: {len(granted)} granted, "
            f"{len(queued)} queued, places in the order taken: {'yes' if in_order else 'NO'}, "
            f"instances given twice: {twice}"
        )
        # the first in the queue waits; the others leave it (the answers came in any order: queued[0] need not be it)
        waiting = min(queued, key=lambda s: s["created"])
        for s in queued:
            if s["id"] != waiting["id"]:
                call(api, "DELETE", s["url"])

        beyond = []
        for k in range(args.waits):
            _s, mine = call(api, "GET", "/api/sessions")
            active = [s for s in mine["mine"] if s["state"] == "active"]
            ended = active[0]
            call(api, "DELETE", ended["url"])
            # from the end the API took: the writes above spent the token's limit, and a refused attempt's wait
            # for its turn is not the pool's (a first run counted it, +2.1 s each)
            began = TAKEN["at"]
            wait("the waiting person's session", lambda w=waiting: active_now(api, w["url"]), every=0.05)
            waited = time.monotonic() - began
            _s, actions = call(api, "GET", f"/api/hosts/{ended['host']}/actions")
            reset = next(
                a
                for a in actions["actions"]
                if a["action"] == "give_back" and a["ids"] == [ended["instance"]] and a.get("ended_at")
            )
            beyond.append(waited - (reset["ended_at"] - reset["accepted_at"]))
            if k + 1 < args.waits:
                _c, waiting = call(api, "POST", "/api/sessions", {})
        print(
            f"the wait beyond the instance's own reset, none free and one waiting, median of {len(beyond)}: "
            f"{statistics.median(beyond):+.2f} s (max {max(beyond):+.2f} s)"
        )
        end_all(api)


if __name__ == "__main__":
    main()
