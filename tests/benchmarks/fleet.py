#!/usr/bin/env python
"""Benchmark: a cold deploy of H fresh hosts (H = 1, 2, 4), pulled straight from the upstream,
through a registry mirror on the LAN, and through the mirror with warm before first start.

For each host count and each way, prints the deploy's wall time, the bytes the upstream served
for the image divided by the image's size (from the stand-in NGC registry's own access log:
H without a mirror, 1 with one, the goal of issue 26), the time from the deploy's start to each
host's first instance being ready, and that instance's own time from its container's start to
its ready line with the caches it found (cold: the stand-in's 3 s; warm: 1 s, given a cache
warmed once for the fleet, isaac_sim_warm_caches). The image is the stand-in Isaac Sim image of
the local registry (123 MB in 6 blobs: far smaller than a real image). The stand-in's cold/warm
gap is small; on a real fleet a cold start compiles shaders for minutes, which only the warm run
then pays.
A script, not a test: timings on shared machines are noisy. Run after ./tools/bootstrap:

    .venv/bin/python tests/benchmarks/fleet.py [--hosts 1 2 4] [--instances 1]
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path

from benchhost import ENV, KEY, ROOT, run

UPSTREAM_LOG = (
    Path(os.environ.get("ISAACSIM_FLEET_REGISTRY_STATE", "/var/lib/isaacsim-fleet/registry")) / "registry.log"
)
ACCESS = re.compile(r'^(?P<addr>\S+) \S+ \S+ \[(?P<when>[^\]]+)\] "GET (?P<path>\S+) [^"]*" 200 (?P<size>\d+)')
BLOB = re.compile(r"/blobs/(sha256:[0-9a-f]{64})$")
MIRROR = "isaacsim-benchmirror-1"


def docker_ip(name: str) -> str:
    out = subprocess.run(
        ["docker", "inspect", "-f", "{{.NetworkSettings.IPAddress}}", name], capture_output=True, text=True, check=True
    )
    return out.stdout.strip()


def image_blobs(image: str) -> dict:
    """{blob digest: bytes} of the image's manifest, as the upstream stores them."""
    repo_tag = image.split("/", 1)[1]
    repo, tag = repo_tag.rsplit(":", 1)
    token = json.loads(
        subprocess.run(
            [
                "curl",
                "-sf",
                "-u",
                f"$oauthtoken:{KEY}",
                f"http://127.0.0.1:5557/token?service=isaacsim-fleet-fixture&scope=repository:{repo}:pull",
            ],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    )["token"]
    manifest = json.loads(
        subprocess.run(
            [
                "curl",
                "-sf",
                "-H",
                f"Authorization: Bearer {token}",
                "-H",
                "Accept: application/vnd.docker.distribution.manifest.v2+json",
                f"http://127.0.0.1:5555/v2/{repo}/manifests/{tag}",
            ],
            capture_output=True,
            text=True,
            check=True,
        ).stdout
    )
    blobs = {layer["digest"]: layer["size"] for layer in manifest["layers"]}
    blobs[manifest["config"]["digest"]] = manifest["config"]["size"]
    return blobs


def served_since(start: float, blobs: dict) -> int:
    """Bytes of the image's blobs the upstream served since start (seconds since the epoch)."""
    total = 0
    for line in UPSTREAM_LOG.read_text(errors="replace").splitlines():
        hit = ACCESS.match(line)
        blob = hit and BLOB.search(hit["path"])
        if blob and blob.group(1) in blobs:
            when = datetime.strptime(hit["when"], "%d/%b/%Y:%H:%M:%S %z").timestamp()
            if when >= int(start):
                total += int(hit["size"])
    return total


def inventory(tmp: Path, hosts: list, mirror: bool, instances: int, image: str, warm: bool) -> Path:
    inv = tmp / "inventory"
    inv.mkdir(exist_ok=True)
    listed = "".join(f"        {h}:\n" for h in hosts)
    text = (
        "all:\n  children:\n    isaac_sim_hosts:\n      hosts:\n"
        f"{listed}"
        "      vars:\n"
        "        ansible_connection: community.docker.docker\n"
        f"        isaac_sim_instance_count: {instances}\n"
        f"        isaac_sim_image: {image}\n"
        "        isaac_sim_web_viewer_image: ''\n"
        "        isaac_sim_rollout_pull_throttle: 0\n"
        f"        isaac_sim_warm_caches: {str(warm).lower()}\n"
        f"        isaac_sim_warm_cache_dir: {tmp}/warm-caches\n"
    )
    if mirror:
        ca = tmp / "ca"
        text += (
            f"        isaac_sim_registry_mirror: {docker_ip(MIRROR)}:5443\n"
            f"        isaac_sim_registry_mirror_upstream: {image.split('/')[0]}\n"
            f"        isaac_sim_registry_mirror_ca: {ca}/ca.crt\n"
            "        isaac_sim_registry_password: ''\n"
            "    isaac_sim_mirror:\n      hosts:\n"
            f"        {MIRROR}:\n"
            "      vars:\n"
            "        ansible_connection: community.docker.docker\n"
            f"        registry_mirror_upstream: http://{image.split('/')[0]}\n"
            f"        registry_mirror_password: {KEY}\n"
            "        registry_mirror_allowed_networks: [172.16.0.0/12]\n"
            f"        registry_mirror_ca_dir: {ca}\n"
        )
    (inv / "hosts.yml").write_text(text)
    if not (inv / "group_vars").exists():
        (inv / "group_vars").symlink_to(ROOT / "inventory" / "demo" / "group_vars")
    return inv


def first_ready(host: str, since: float) -> tuple:
    """(seconds from since to the host's instance 0 ready marker, seconds from its container's start to
    that marker, the caches it found: warm or cold); None where not known."""
    out = subprocess.run(
        [
            "docker",
            "exec",
            host,
            "sh",
            "-c",
            "cat /run/isaac-sim/instance-0.ready /run/isaac-sim/instance-0.cache; "
            "docker inspect -f '{{.State.StartedAt}}' isaac-sim-0",
        ],
        capture_output=True,
        text=True,
        check=False,
    )
    parts = out.stdout.split()
    if out.returncode != 0 or len(parts) != 3:
        return None, None, None
    ready = float(parts[0])
    started = datetime.fromisoformat(parts[2][:26].rstrip("Z") + "+00:00").timestamp()
    return ready - since, ready - started, parts[1]


def one(count: int, mirror: bool, instances: int, image: str, blobs: dict, warm: bool) -> dict:
    hosts = [f"isaacsim-benchfleet-{i}" for i in range(1, count + 1)]
    made = hosts + ([MIRROR] if mirror else [])
    names = json.dumps({"testbed_hosts": made})
    run(["ansible-playbook", "molecule/resources/destroy.yml", "-e", names])
    run(["ansible-playbook", "molecule/resources/create.yml", "-e", names], check=True)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            inv = inventory(Path(tmp), hosts, mirror, instances, image, warm)
            start = time.time()
            proc = run(["ansible-playbook", "-i", str(inv), str(ROOT / "playbooks" / "deploy.yml")])
            wall = time.time() - start
            if proc.returncode != 0:
                sys.exit(f"the deploy failed:\n{proc.stdout[-3000:]}{proc.stderr}")
            ready = [first_ready(h, start) for h in hosts]
            served = served_since(start, blobs)
    finally:
        run(["ansible-playbook", "molecule/resources/destroy.yml", "-e", names])
    return {
        "hosts": count,
        "mirror": mirror,
        "wall_s": round(wall, 1),
        "upstream_ratio": round(served / sum(blobs.values()), 2),
        "warm": warm,
        "first_ready": ready,
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--hosts", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--instances", type=int, default=1)
    parser.add_argument("--image", default="172.17.0.1:5555/fixtures/isaac-sim-standin:6.0.1")
    args = parser.parse_args()
    blobs = image_blobs(args.image)
    print(f"image {args.image}: {sum(blobs.values()) / 1e6:.0f} MB in {len(blobs)} blobs")
    head = f"{'hosts':>5} {'way':>11} {'wall s':>7} {'upstream/image':>14}"
    print(f"{head}  per host: first ready s (start to ready s, caches)")
    for count in args.hosts:
        for mirror, warm in ((False, False), (True, False), (True, True)):
            r = one(count, mirror, args.instances, args.image, blobs, warm)
            way = ("mirror" if mirror else "direct") + ("+warm" if warm else "")
            ready = ", ".join(
                "-" if first is None else f"{first:.0f} ({own:.0f}, {cache})" for first, own, cache in r["first_ready"]
            )
            print(f"{r['hosts']:>5} {way:>11} {r['wall_s']:>7} {r['upstream_ratio']:>14}  {ready}")
            sys.stdout.flush()


if __name__ == "__main__":
    ENV.setdefault("ANSIBLE_NOCOLOR", "1")
    main()
