#!/usr/bin/env python
"""Benchmark: what one isaac_sim_info call costs on a host of N = 1, 4 and 8 instances.

Prints, for each N:
  - the processes the module spawns per call, counted from outside by strace
    (every execve of the module's process tree) next to the module's own count;
  - the module's time on the host as a ratio to the bare pair it replaces:
    one `systemctl show` of the units and one `docker inspect` of the containers;
and at N = 4 the time of a playbook with the module against a naive one that
runs ansible.builtin.systemd_service and community.docker.docker_container_info
once per instance, beside the floor of any such play (the same play with
ansible.builtin.ping, and a play with no task), the plays taken in turn, medians
of --play-runs. Then where the module's own time goes, per N: the imports it
pays beyond the ping module's (python -X importtime, the collection's own
module_utils apart), and each part of the status read as the module reports it
(timings_ms: env files, Docker, GPU, systemd, building records, the journal's
events, log tails), medians over the runs.

A script, not a test: timings on shared machines are noisy. Needs strace and
nsenter on the machine that runs it. Run after ./tools/bootstrap:

    .venv/bin/python tests/benchmarks/status.py [--runs 10] [--play-runs 5]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import subprocess
import sys
import time

from benchhost import ENV, ROOT, bench_host, run, timed_play

HOST = "isaacsim-bench-1"
PAYLOAD = "/root/bench_isaac_sim_info.py"
PING = "/root/bench_ping.py"

MODULE_PLAY = """- name: Status with isaac_sim_info (one call)
  hosts: isaac_sim_hosts
  gather_facts: false
  tasks:
    - name: Read every instance
      isaacsim.fleet.isaac_sim_info:
"""

NAIVE_PLAY = """- name: Status the naive way (two module calls per instance)
  hosts: isaac_sim_hosts
  gather_facts: false
  tasks:
    - name: Read each unit
      ansible.builtin.systemd_service:
        name: "isaac-sim@{{ item }}.service"
      loop: "{{ range(N) | list }}"
    - name: Read each container
      community.docker.docker_container_info:
        name: "isaac-sim-{{ item }}"
      loop: "{{ range(N) | list }}"
"""

PING_PLAY = MODULE_PLAY.replace("isaacsim.fleet.isaac_sim_info:", "ansible.builtin.ping:")
EMPTY_PLAY = """- name: Nothing (ansible-playbook's own start)
  hosts: isaac_sim_hosts
  gather_facts: false
  tasks: []
"""

# runs inside the host: median wall time of each command over `runs` runs
TIMER = r"""
import json, statistics, subprocess, sys, time
cmds, runs = json.loads(sys.argv[1]), int(sys.argv[2])
out = {}
for name, cmd in cmds.items():
    times = []
    for _n in range(runs):
        t = time.perf_counter()
        subprocess.run(cmd, shell=True, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        times.append(time.perf_counter() - t)
    out[name] = statistics.median(times)
print(json.dumps(out))
"""


# runs inside the host: median self time (ms) of the imports of each payload, by who owns them
IMPORTS = r"""
import json, re, statistics, subprocess, sys
paths, runs = json.loads(sys.argv[1]), int(sys.argv[2])
line = re.compile(r"import time:\s+(\d+) \|\s+\d+ \|\s*(\S+)")
def groups(path):
    err = subprocess.run([sys.executable, "-X", "importtime", path], capture_output=True, text=True).stderr
    out = {"collection": 0.0, "ansible": 0.0, "stdlib": 0.0}
    for m in map(line.match, err.splitlines()):
        if m:
            name = m.group(2)
            key = "stdlib" if not name.startswith("ansible") else "ansible"
            key = "collection" if name.startswith("ansible_collections") else key
            out[key] += int(m.group(1)) / 1000
    return out
res = {}
for name, path in paths.items():
    each = [groups(path) for _n in range(runs)]
    res[name] = {k: statistics.median(g[k] for g in each) for k in each[0]}
print(json.dumps(res))
"""

PARTS = ("files", "docker", "gpu", "systemd", "build", "events", "logs")


def sh(cmd):
    return subprocess.run(["docker", "exec", HOST, "sh", "-c", cmd], capture_output=True, text=True, check=True).stdout


def deploy(inv, n):
    timed_play(inv, ROOT / "playbooks" / "deploy.yml", HOST, ["-e", json.dumps({"isaac_sim_instance_count": n})])


def keep_payload(inv, module, dest):
    """The module as Ansible ships it to the host (AnsiballZ, arguments inside), kept for direct runs."""
    env = dict(ENV, ANSIBLE_KEEP_REMOTE_FILES="1")
    proc = run(["ansible", "-i", str(inv), HOST, "-m", module], env=env)
    if proc.returncode != 0:
        sys.exit(f"{module} failed:\n{proc.stdout[-2000:]}{proc.stderr}")
    short = module.rsplit(".", 1)[-1]
    sh(f"cp $(ls -t /root/.ansible/tmp/ansible-tmp-*/AnsiballZ_{short}.py | head -1) {dest}")


def module_result():
    return json.loads(sh(f"python3 {PAYLOAD}"))


def breakdown(runs):
    """Median ms of the module's imports beyond ping's, and of each part of its status read."""
    imports = json.loads(sh(f"python3 -c '{IMPORTS}' '{json.dumps({'module': PAYLOAD, 'ping': PING})}' {runs}"))
    reads = [module_result()["timings_ms"] for _n in range(runs)]
    parts = {part: statistics.median(r.get(part, 0.0) for r in reads) for part in PARTS}
    extra = {k: imports["module"][k] - imports["ping"][k] for k in imports["module"]}
    return extra, parts


def spawns_by_strace():
    """execve calls in the module's process tree, minus nsenter and the module's own python."""
    pid = subprocess.run(
        ["docker", "inspect", "-f", "{{.State.Pid}}", HOST], capture_output=True, text=True, check=True
    ).stdout.strip()
    trace = subprocess.run(
        [
            "strace",
            "-f",
            "-qq",
            "-e",
            "trace=execve",
            "-e",
            "signal=none",
            "-o",
            "/dev/stdout",
            "nsenter",
            "-t",
            pid,
            "-m",
            "-u",
            "-i",
            "-n",
            "-p",
            "--",
            "python3",
            PAYLOAD,
        ],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    execs = [line for line in trace.splitlines() if "execve(" in line and "= 0" in line]
    binaries = [line.split('execve("', 1)[1].split('"', 1)[0] for line in execs]
    # the first two are nsenter itself and the python3 it starts
    return binaries[2:]


def empty_play(inv, path):
    """Seconds of a play with no task (its recap names no host, so timed_play cannot read it)."""
    start = time.monotonic()
    run(["ansible-playbook", "-i", str(inv), str(path)], check=True)
    return time.monotonic() - start


def compare_plays(inv, tmp, runs):
    """Median seconds of each play, the plays taken in turn so a slow spell of the machine falls on all.

    Besides the module's play and the naive one: the same play with ansible.builtin.ping (the floor
    of any one-module play: ansible-playbook's start, interpreter discovery, one call) and a play
    with no task (ansible-playbook's start alone)."""
    books = {
        "module": MODULE_PLAY,
        "naive": NAIVE_PLAY.replace("range(N)", "range(4)"),
        "ping": PING_PLAY,
        "empty": EMPTY_PLAY,
    }
    paths = {}
    for name, text in books.items():
        paths[name] = tmp / f"{name}.yml"
        paths[name].write_text(text)
    times = {name: [] for name in books}
    for _n in range(runs):
        for name, path in paths.items():
            times[name].append(timed_play(inv, path, HOST)[0] if name != "empty" else empty_play(inv, path))
    return {name: statistics.median(each) for name, each in times.items()}


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=10, help="runs to take the median of")
    parser.add_argument("--play-runs", type=int, default=5, help="runs of each play (N = 4) to take the median of")
    args = parser.parse_args()
    for tool in ("strace", "nsenter"):
        if not shutil.which(tool):
            sys.exit(f"{tool} is needed (apt-get install {'strace' if tool == 'strace' else 'util-linux'})")

    rows, plays = [], {}
    with bench_host(HOST) as (inv, tmp):
        for n in (1, 4, 8):
            deploy(inv, n)
            keep_payload(inv, "isaacsim.fleet.isaac_sim_info", PAYLOAD)
            keep_payload(inv, "ansible.builtin.ping", PING)
            result = module_result()
            assert result["summary"]["configured"] == n and result["summary"]["ready"] == n, result["summary"]
            spawned = spawns_by_strace()
            units = " ".join(f"isaac-sim@{i}.service" for i in range(n))
            names = " ".join(f"isaac-sim-{i}" for i in range(n))
            bare = (
                f"systemctl show -p Id,ActiveState,SubState,UnitFileState,NRestarts {units} >/dev/null; "
                f"docker inspect {names} >/dev/null"
            )
            times = json.loads(
                sh(
                    f"python3 -c '{TIMER}' "
                    f"'{json.dumps({'module': f'python3 {PAYLOAD}', 'bare': bare, 'ping': f'python3 {PING}'})}' "
                    f"{args.runs}"
                )
            )
            rows.append((n, spawned, result["cost"], times, breakdown(args.runs)))
            if n == 4:
                plays = compare_plays(inv, tmp, args.play_runs)

    print("status benchmark: isaac_sim_info on one host, stand-in instances, no GPU")
    print("times on the host, median of each; ping = Ansible's own ping module, the floor any module pays")
    print(
        f"{'N':>2}  {'spawns (strace)':<16} {'(module says)':<14} {'module':>8} {'bare pair':>10} {'ratio':>7}"
        f" {'ping':>7} {'module-ping':>12} {'ratio':>6}  spawned"
    )
    for n, spawned, cost, t, _parts in rows:
        own = t["module"] - t["ping"]
        print(
            f"{n:>2}  {len(spawned):<16} {cost['spawns']:<14} {t['module'] * 1000:6.0f}ms "
            f"{t['bare'] * 1000:8.0f}ms {t['module'] / t['bare']:6.2f}x {t['ping'] * 1000:5.0f}ms"
            f" {own * 1000:10.0f}ms {own / t['bare']:5.2f}x  {', '.join(spawned)}"
        )
    print(f"docker API calls per module call: {', '.join(str(c['docker_api_calls']) for _n, _s, c, _t, _p in rows)}")
    print("\nwhere module-ping goes (ms, medians): imports beyond ping's, then each part of the status read")
    print(
        f"{'N':>2}  {'imp:coll':>8} {'imp:ansible':>11} {'imp:stdlib':>10}"
        + "".join(f" {p:>8}" for p in PARTS)
        + f" {'rest':>7}"
    )
    for n, _s, _c, t, (extra, parts) in rows:
        rest = (t["module"] - t["ping"]) * 1000 - sum(extra.values()) - sum(parts.values())
        print(
            f"{n:>2}  {extra['collection']:8.1f} {extra['ansible']:11.1f} {extra['stdlib']:10.1f}"
            + "".join(f" {parts[p]:8.1f}" for p in PARTS)
            + f" {rest:7.1f}"
        )
    grows = len({len(s) for _n, s, _c, _t, _p in rows}) > 1
    print(f"spawns grow with N: {'YES' if grows else 'no'}")
    print(
        f"N=4 playbook, median of {args.play_runs}, taken in turn: module {plays['module']:.2f} s, "
        f"naive per-instance {plays['naive']:.2f} s, module / naive = {plays['module'] / plays['naive']:.2f}x"
    )
    print(
        f"  the floor: the same play with ansible.builtin.ping {plays['ping']:.2f} s "
        f"({plays['ping'] / plays['naive']:.2f}x of naive), a play with no task {plays['empty']:.2f} s; "
        f"the module's play costs {plays['module'] - plays['ping']:.2f} s more than ping's"
    )
    return 1 if grows else 0


if __name__ == "__main__":
    sys.exit(main())
