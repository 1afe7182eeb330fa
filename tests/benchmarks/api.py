#!/usr/bin/env python
"""Benchmark: the fleet's API on a test fleet of 3 hosts x 4 stand-in instances, the first host also
the front door (issue 44, item 7).

Prints:
- the fleet listing (GET /api/fleet with a token, through nginx) at 20 concurrent clients, p50 and
  p95, beside the slowest host's own status answer (GET :8290/status from this machine, the median of
  10), and their ratio;
- an action's acknowledgement: the time to the 202 of POST .../restart (p50 and max of 5);
- a restart through the API (the POST to the end of its events, the instance ready) against the same
  restart on the host (`systemctl restart`, which returns once the readiness gate saw the ready
  line; through `docker exec`, whose own cost is printed too), medians of 5, their difference (the
  goal: the API adds at most 1 s) and ratio;
- a host that does not answer (the third, frozen with `docker pause`): the time of the first listing
  that names it unreachable, once past the API's reuse of its last read (goal: within 5 s), and the
  listing at the same concurrency while it stays frozen.

A script, not a test: timings on shared machines are noisy. Run after ./tools/bootstrap:

    .venv/bin/python tests/benchmarks/api.py [--clients 20] [--requests 10] [--restarts 5]
"""

from __future__ import annotations

import argparse
import http.client
import importlib.util
import json
import ssl
import statistics
import subprocess
import sys
import threading
import time
import urllib.request

from benchhost import KEY_VAR, ROOT, bench_host, run

HOSTS = [f"isaacsim-benchapi-{i}" for i in (1, 2, 3)]
INSTANCES = 4


def docker_ip(name: str) -> str:
    out = subprocess.run(
        ["docker", "inspect", "-f", "{{.NetworkSettings.IPAddress}}", name], capture_output=True, text=True, check=True
    )
    return out.stdout.strip()


def door_auth():
    # the checkout as the collection, as tests/conftest.py makes it importable
    link = ROOT / ".ansible" / "collections" / "ansible_collections" / "isaacsim" / "fleet"
    if not link.exists():
        link.parent.mkdir(parents=True, exist_ok=True)
        link.symlink_to("../../../..")
    sys.path.insert(0, str(ROOT / ".ansible" / "collections"))
    return importlib.import_module("ansible_collections.isaacsim.fleet.plugins.module_utils.front.door_auth")


def play(inv, playbook, *extra):
    start = time.monotonic()
    proc = run(["ansible-playbook", "-i", str(inv), *KEY_VAR, *extra, str(ROOT / "playbooks" / playbook)])
    if proc.returncode != 0:
        sys.exit(f"{playbook} failed:\n{proc.stdout[-4000:]}{proc.stderr[-2000:]}")
    return time.monotonic() - start


class Door:
    def __init__(self, address: str, ca: str, token: str):
        self.address, self.token = address, token
        self.ctx = ssl.create_default_context(cafile=ca)

    def call(self, method: str, path: str, body=None, timeout: float = 60):
        conn = http.client.HTTPSConnection(self.address, 443, context=self.ctx, timeout=timeout)
        headers = {"Authorization": f"Bearer {self.token}", "Content-Type": "application/json"}
        try:
            conn.request(method, path, body=json.dumps(body) if body is not None else None, headers=headers)
            answer = conn.getresponse()
            data = answer.read()
            return answer.status, data
        finally:
            conn.close()


def percentile(values, q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(round(q * (len(ordered) - 1))))]


def listing(door: Door, clients: int, requests: int) -> list:
    """Seconds of each GET /api/fleet, `clients` at once, `requests` each."""
    times, lock, failures = [], threading.Lock(), []

    def client():
        for _request in range(requests):
            began = time.monotonic()
            status, _data = door.call("GET", "/api/fleet")
            took = time.monotonic() - began
            with lock:
                (times if status == 200 else failures).append(took)

    threads = [threading.Thread(target=client) for _client in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    if failures:
        sys.exit(f"{len(failures)} fleet listings failed")
    return times


def status_answer(address: str, n: int = 10) -> float:
    took = []
    for _try in range(n):
        began = time.monotonic()
        with urllib.request.urlopen(f"http://{address}:8290/status", timeout=10) as answer:
            answer.read()
        took.append(time.monotonic() - began)
    return statistics.median(took)


def restart_through_api(door: Door, host: str, n: int) -> tuple:
    """(seconds to the 202, seconds to the end of the action's events) of one restart of instance n."""
    began = time.monotonic()
    status, data = door.call("POST", f"/api/hosts/{host}/instances/{n}/restart")
    acked = time.monotonic() - began
    if status != 202:
        sys.exit(f"the restart was not taken: {status} {data[:300]!r}")
    answer = json.loads(data)
    status, stream = door.call("GET", answer["events"], timeout=300)
    ended = time.monotonic() - began
    last = json.loads(stream.decode().splitlines()[-1])
    if status != 200 or last["state"] != "succeeded":
        sys.exit(f"the restart did not succeed: {last}")
    return acked, ended


def on_the_host(host: str, command: str) -> float:
    began = time.monotonic()
    subprocess.run(["docker", "exec", host, "sh", "-c", command], check=True, capture_output=True)
    return time.monotonic() - began


def door_fleet(inv, tmp, hosts: list, instances: int, scopes: list, door_settings=None) -> Door:
    """Deploys the hosts (instances each, with their action agents), the front door on the first, and
    makes olga's token of those scopes: the API as that token reaches it."""
    door_host, door_ip = hosts[0], docker_ip(hosts[0])
    hashed = door_auth().hash_password("bench-secret", 10000)
    settings = {
        "isaac_sim_instance_count": instances,
        "isaac_sim_web_viewer_image": "",
        "isaac_sim_rollout_soak": 0,
        "isaac_sim_status_server_logs_allow": [f"{door_ip}/32"],
        "isaac_sim_agent_enabled": True,
        "isaac_sim_agent_allow": [f"{door_ip}/32"],
        "isaac_sim_agent_ca_dir": str(tmp / "ca"),
    }
    door = {
        "front_door_users": [{"name": "olga", "role": "operator", "password_hash": hashed}],
        "front_door_ca_dir": str(tmp / "ca"),
        "front_door_server_name": door_ip,
        "front_door_turn": False,
        **(door_settings or {}),
    }
    # the door's group; every setting as extra vars, which win over the demo's group_vars
    (inv / "bench.yml").write_text(json.dumps({"isaac_sim_front_door": {"hosts": {door_host: {}}}}))
    given = ["-e", json.dumps({**settings, **door})]
    print(f"deploy of {len(hosts)} hosts x {instances} instances: {play(inv, 'deploy.yml', *given):.0f} s")
    print(f"front door on {door_host} ({door_ip}): {play(inv, 'front_door.yml', *given):.0f} s")
    made = {
        "front_door_token_state": "present",
        "front_door_token_user": "olga",
        "front_door_token_name": "bench",
        "front_door_token_scopes": scopes,
        "front_door_token_dir": str(tmp / "tokens"),
    }
    play(inv, "front_door_token.yml", *given, "-e", json.dumps(made))
    [token] = (tmp / "tokens").glob("*-olga-bench.token")
    return Door(door_ip, str(tmp / "ca" / "ca.crt"), token.read_text().strip())


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--clients", type=int, default=20)
    parser.add_argument("--requests", type=int, default=10, help="fleet listings per client")
    parser.add_argument("--restarts", type=int, default=5)
    args = parser.parse_args()
    with bench_host(HOSTS) as (inv, tmp):
        api = door_fleet(inv, tmp, HOSTS, INSTANCES, ["read", "act", "operate"])

        status, data = api.call("GET", "/api/fleet")
        fleet = json.loads(data)
        ready = sum(1 for h in fleet["hosts"] for i in h["instances"] if i["ready"])
        print(f"the fleet through the API: {len(fleet['hosts'])} hosts, {ready} instances ready (HTTP {status})")

        times = listing(api, args.clients, args.requests)
        p50, p95 = percentile(times, 0.5), percentile(times, 0.95)
        slowest = max(status_answer(docker_ip(h)) for h in HOSTS)
        print(
            f"fleet listing, {args.clients} clients x {args.requests}: p50 {p50 * 1000:.0f} ms, "
            f"p95 {p95 * 1000:.0f} ms; "
            f"the slowest host's own status answer {slowest * 1000:.0f} ms; p50/host {p50 / slowest:.2f}x, "
            f"p95/host {p95 / slowest:.2f}x"
        )

        acks, through_api, direct = [], [], []
        exec_floor = statistics.median(on_the_host(HOSTS[1], "true") for _try in range(5))
        for _run in range(args.restarts):
            acked, ended = restart_through_api(api, HOSTS[1], 2)
            acks.append(acked)
            through_api.append(ended)
            direct.append(on_the_host(HOSTS[1], "systemctl restart isaac-sim@2.service"))
        api_s, host_s = statistics.median(through_api), statistics.median(direct)
        print(f"action acknowledged (202): p50 {percentile(acks, 0.5) * 1000:.0f} ms, max {max(acks) * 1000:.0f} ms")
        print(
            f"restart of one instance, medians of {args.restarts}: through the API {api_s:.2f} s, systemctl restart "
            f"with its readiness gate on the host {host_s:.2f} s (docker exec alone {exec_floor:.2f} s); the API adds "
            f"{api_s - host_s:+.2f} s ({api_s - (host_s - exec_floor):+.2f} s against the bare restart), "
            f"{api_s / host_s:.2f}x"
        )

        frozen = HOSTS[2]
        subprocess.run(["docker", "pause", frozen], check=True, capture_output=True)
        try:
            time.sleep(2.5)  # past the API's reuse of its last read (2 s)
            began = time.monotonic()
            status, data = api.call("GET", "/api/fleet")
            first = time.monotonic() - began
            reach = {h["name"]: (h["reachable"], h["error"]) for h in json.loads(data)["hosts"]}
            if status != 200 or reach[frozen][0] or not all(r for n, (r, _e) in reach.items() if n != frozen):
                sys.exit(f"with {frozen} frozen the listing said: {status} {reach}")
            times = listing(api, args.clients, args.requests)
        finally:
            subprocess.run(["docker", "unpause", frozen], check=True, capture_output=True)
        print(
            f"{frozen} frozen (docker pause): the first listing named it unreachable in {first * 1000:.0f} ms "
            f"(goal: within 5 s; it said {reach[frozen][1]!r}); then {args.clients} clients x {args.requests}: "
            f"p50 {percentile(times, 0.5) * 1000:.0f} ms, p95 {percentile(times, 0.95) * 1000:.0f} ms"
        )


if __name__ == "__main__":
    main()
