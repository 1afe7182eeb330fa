"""Run the plan's GPU reading and placement on a real NVIDIA GPU host, as the isaac_sim_plan module does.

Not part of the test suite (CI has no GPU): run it by hand on a GPU host, as root.

    python3 tests/hardware/placement_check.py [--alloc-mib 4096] [--out DIR]

What it does, with the module's own code (instance/host_facts.py, nvenc.py, placement.py):
  1. starts a process holding --alloc-mib on GPU 0 (PyTorch) in a cgroup named like a Docker
     container's, so the plan sees memory held by a process that is, or is not, the collection's;
  2. reads the host's GPUs as the plan does: nvidia-smi -q -x, then the driver's encode API
     (a child process), then again from the encoder cache (both timed);
  3. plans streaming and headless 6.x instances on it, and prints each plan or refusal;
  4. with --out keeps the raw nvidia-smi XML and the encoder probe's output of this same GPU,
     for tests/unit/recorded, and a JSON report.
It fails unless the memory held by the process counts against the GPU when the process is not
ours and not when it is, and the encode API gives a definite answer (True or False).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
_TREE = Path(tempfile.mkdtemp(prefix="placement-check-"))
(_TREE / "ansible_collections" / "isaacsim").mkdir(parents=True)
(_TREE / "ansible_collections" / "isaacsim" / "fleet").symlink_to(ROOT)
sys.path.insert(0, str(_TREE))

from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import host_facts, nvenc  # noqa: E402

sys.path.insert(0, str(ROOT / "tests" / "hardware"))
import gpu_check  # noqa: E402  (the allocating process and the stand-in container cgroup)


class Docker:
    """Docker's API as the plan asks it: our containers are the ids given."""

    def __init__(self, ids):
        self.ids = ids

    def image(self, ref):
        return {"Id": "sha256:" + "0" * 64}

    def containers(self, name_prefix):
        return [{"Id": i} for i in self.ids]

    def network(self, name):
        return None


def params(data_root, config_dir, systemd_dir, **over):
    """The isaac_sim role's variables as the module passes them (its argument spec's defaults)."""
    p = {
        "release": "6.x",
        "image": "nvcr.io/nvidia/isaac-sim:6.0.1",
        "instance_count": 2,
        "max_instances": 8,
        "scale_to_zero": False,
        "port_bases": {},
        "port_stride": 1,
        "gpu_enabled": True,
        "gpu_map": {},
        "gpu_exclusive": False,
        "gpu_memory": "",
        "instance_gpu_memory": {},
        "gpu_consumer_encode_sessions": 8,
        "memory_limit": "8g",
        "shm_size": "2g",
        "data_root": str(data_root),
        "public_address": "10.0.0.5",
        "ready_pattern": None,
        "accept_eula": True,
        "privacy_consent": False,
        "env": {},
        "secret_env_names": [],
        "docker_args": [],
        "allowed_docker_args": [],
        "app_args": [],
        "ready_timeout": 300,
        "stop_timeout": 60,
        "restart_sec": 10,
        "start_limit_burst": 5,
        "health_interval": 30,
        "health_retries": 3,
        "unhealthy_restart": 300,
        "image_pull": "never",
        "registry_login": False,
        "check_host_ports": False,
        "companions": [],
        "profile": "streaming",
        "instance_profiles": {},
        "status_server": {"enabled": False},
        "hub_cache": {"enabled": False},
        "firewall": True,
        "allowed_networks": ["10.0.0.0/8"],
        "allowed_networks_by_port": {},
        "web_viewer_image": "",
        "network_mode": "host",
        "macvlan_parent": "",
        "macvlan_subnet": "",
        "macvlan_gateway": "",
        "address_pool": [],
        "instance_addresses": {},
        "config_dir": str(config_dir),
        "systemd_dir": str(systemd_dir),
    }
    p.update(over)
    return p


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--alloc-mib", type=int, default=4096)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="placement-"))
    for name in ("data", "etc", "systemd"):
        (work / name).mkdir()
    problems, report = [], {}

    def probe(ids, runs):
        def run(argv):
            start = time.perf_counter()
            proc = subprocess.run(argv, capture_output=True, text=True, check=False)
            runs.append({"argv": argv[:2], "ms": round((time.perf_counter() - start) * 1000, 1), "out": proc.stdout})
            return proc.returncode, proc.stdout, proc.stderr

        return host_facts.Probe(
            # Docker's API is the stand-in above: the plan asks it where the docker command is installed
            lambda name: "/usr/bin/docker" if name == "docker" else shutil.which(name),
            run,
            Docker(ids),
            lambda: "10.0.0.5",
            python=sys.executable,
        )

    def p(**over):
        return params(work / "data", work / "etc", work / "systemd", **over)

    # --alloc-mib 0: no process of its own (a dry run against a stand-in driver)
    child = None
    if args.alloc_mib:
        child = subprocess.Popen(
            [sys.executable, "-c", gpu_check.ALLOCATOR, str(args.alloc_mib)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
        )
    in_cgroup = None
    try:
        if child:
            line = child.stdout.readline().strip()
            if not line.startswith("allocated"):
                sys.exit(f"the allocating process did not start: {line!r}")
            in_cgroup = gpu_check.into_fake_container(child.pid)
            print(f"process {child.pid} {line}: {args.alloc_mib} MiB on GPU 0 (container cgroup: {bool(in_cgroup)})")

        runs_cold = []
        start = time.perf_counter()
        cold = host_facts.facts(probe([], runs_cold), p())
        report["facts_cold_ms"] = round((time.perf_counter() - start) * 1000, 1)
        runs_warm = []
        start = time.perf_counter()
        warm = host_facts.facts(probe([], runs_warm), p())
        report["facts_warm_ms"] = round((time.perf_counter() - start) * 1000, 1)
        ours = host_facts.facts(probe([gpu_check.FAKE_CONTAINER_ID] if in_cgroup else [], []), p())
        report.update(gpus_cold=cold["gpus"], gpus_warm=warm["gpus"], gpus_ours=ours["gpus"])
        report["commands_cold"] = [(r["argv"][0].rsplit("/", 1)[-1], r["ms"]) for r in runs_cold]
        report["commands_warm"] = [(r["argv"][0].rsplit("/", 1)[-1], r["ms"]) for r in runs_warm]
        smi_xml = next((r["out"] for r in runs_cold if r["argv"][0].endswith("nvidia-smi")), "")
        probe_out = next((r["out"] for r in runs_cold if r["argv"][1:2] == ["-c"]), "")
        print(f"facts, cold (encoder probe): {report['facts_cold_ms']} ms: {report['commands_cold']}")
        print(f"facts, warm (encoder cache): {report['facts_warm_ms']} ms: {report['commands_warm']}")
        for gpu in cold["gpus"]:
            print(f"  {json.dumps(gpu)}")
        g0 = cold["gpus"][0]
        if g0["encoder"] is None:
            problems.append(f"the encode API gave no answer for GPU 0: {g0.get('encoder_why')}")
        if g0["others_mib"] < args.alloc_mib:
            counted = g0["others_mib"]
            problems.append(f"a process that is not ours holds {args.alloc_mib} MiB, the plan counts {counted}")
        if in_cgroup and ours["gpus"][0]["others_mib"] != 0:
            problems.append(f"our own container's memory counted as others': {ours['gpus'][0]['others_mib']} MiB")
        probed_again = any(r["argv"][1:2] == ["-c"] for r in runs_warm)
        if [g["encoder"] for g in warm["gpus"]] != [g["encoder"] for g in cold["gpus"]] or probed_again:
            problems.append(f"the cache did not answer as the probe did: {report['commands_warm']}")

        for name, over in (
            ("2 streaming", {}),
            ("4 headless at 16g", {"instance_count": 4, "profile": "headless"}),
            ("6 headless at 16g", {"instance_count": 6, "profile": "headless"}),
        ):
            try:
                out = host_facts.plan_host(probe([], []), p(**over))
                answer = {"gpus": [i["gpu"] for i in out["plan"]["instances"]], "warnings": out["warnings"]}
            except host_facts.PlanRefusedError as exc:
                answer = {"refused": exc.fields.get("errors")}
            report[f"plan: {name}"] = answer
            print(f"plan, {name}: {json.dumps(answer)}")
    finally:
        if in_cgroup:
            gpu_check.leave_fake_container(child.pid, in_cgroup)
        if child:
            child.stdin.close()
            child.wait(timeout=60)

    found, why = nvenc.read(probe_out)
    report["nvenc"] = {"found": found, "why": why}
    report["problems"] = problems
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "nvidia-smi-q-x.xml").write_text(smi_xml)
        (args.out / "nvenc-probe.json").write_text(probe_out)
        (args.out / "placement_check.json").write_text(json.dumps(report, indent=1))
    for problem in problems:
        print("PROBLEM:", problem)
    print("placement_check:", "FAILED" if problems else "all checks passed")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
