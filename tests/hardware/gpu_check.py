"""Run the collection's GPU code on a real NVIDIA GPU and check it against the driver's own view.

Not part of the test suite (CI has no GPU): run it by hand on a GPU host, as root.

    python3 tests/hardware/gpu_check.py [--alloc-mib 4096] [--out DIR]

What it does:
  1. lists the GPUs with the query the driver check uses and runs that check
     against each release's minimum driver;
  2. starts a process that allocates --alloc-mib on GPU 0 (PyTorch, else CuPy)
     and, when cgroup v2 is writable, moves it into a cgroup named like a Docker
     container's scope, so container_of_pid is tried against the real kernel;
  3. reads per-process GPU memory through NVML and through `nvidia-smi -q -x`;
  4. fails unless both sources see that process on GPU 0 with at least the
     memory it allocated, agree on the GPUs and their used memory, and the
     cgroup maps back to the id.
With --out it keeps the raw driver outputs (for tests/unit/recorded) and a JSON report.
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
# the collection as Ansible imports it: ansible_collections/isaacsim/fleet -> this checkout
_TREE = Path(tempfile.mkdtemp(prefix="gpu-check-"))
(_TREE / "ansible_collections" / "isaacsim").mkdir(parents=True)
(_TREE / "ansible_collections" / "isaacsim" / "fleet").symlink_to(ROOT)
sys.path.insert(0, str(_TREE))

from ansible_collections.isaacsim.fleet.plugins.module_utils.host import driver  # noqa: E402
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import gpu_usage  # noqa: E402
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import hostprobe  # noqa: E402
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance.releases import RELEASES  # noqa: E402

# a made-up container id: the cgroup below stands in for a container, no container runs
FAKE_CONTAINER_ID = "15aac51a" * 8
CGROUP = Path("/sys/fs/cgroup/system.slice") / f"docker-{FAKE_CONTAINER_ID}.scope"

ALLOCATOR = """
import sys, time
mib = int(sys.argv[1])
try:
    import torch
    block = torch.empty(mib * 1024 * 1024, dtype=torch.uint8, device="cuda:0")
    block.fill_(1); torch.cuda.synchronize(); how = "torch " + torch.__version__
except ImportError:
    import cupy
    block = cupy.ones(mib * 1024 * 1024, dtype=cupy.uint8); cupy.cuda.Device(0).synchronize()
    how = "cupy " + cupy.__version__
print("allocated", how, flush=True)
sys.stdin.read()  # hold the memory until the parent closes stdin
"""


def run(argv):
    proc = subprocess.run(argv, capture_output=True, text=True, check=False)
    return proc.returncode, proc.stdout, proc.stderr


def import_nvml():
    import pynvml  # nvidia-ml-py

    return pynvml


def timed(fn, *args):
    start = time.perf_counter()
    value = fn(*args)
    return value, round((time.perf_counter() - start) * 1000, 1)


def into_fake_container(pid):
    """Move pid into a cgroup named like a Docker scope: its old cgroup, or None when that cannot be done."""
    try:
        old = Path(f"/proc/{pid}/cgroup").read_text().strip().split("::", 1)[1]
        CGROUP.mkdir(parents=True, exist_ok=True)
        (CGROUP / "cgroup.procs").write_text(f"{pid}\n")
        return old
    except (OSError, IndexError) as exc:
        print(f"  (no stand-in container cgroup: {exc})")
        return None


def leave_fake_container(pid, old):
    try:
        (Path("/sys/fs/cgroup" + old) / "cgroup.procs").write_text(f"{pid}\n")
        CGROUP.rmdir()
    except OSError:
        pass


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--alloc-mib", type=int, default=4096)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args()
    if not shutil.which("nvidia-smi"):
        sys.exit("nvidia-smi is not on PATH: this check needs a host with an NVIDIA GPU and driver")
    problems, report = [], {}

    rc, csv, err = run(hostprobe.GPU_QUERY)
    gpus = hostprobe.parse_gpu_list(csv)
    report["driver_check"] = {
        release: driver.check(gpus, spec["min_driver"], release) or "ok" for release, spec in RELEASES.items()
    }
    print("GPUs (driver check's query):", json.dumps(gpus))
    for release, verdict in report["driver_check"].items():
        print(f"  Isaac Sim {release}: minimum {RELEASES[release]['min_driver']}: {verdict}")
    if not gpus:
        problems.append(f"the driver check's query found no GPU (rc {rc}: {err.strip()})")

    in_cgroup = None
    child = subprocess.Popen(
        [sys.executable, "-c", ALLOCATOR, str(args.alloc_mib)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        line = child.stdout.readline().strip()
        if not line.startswith("allocated"):
            sys.exit(f"the allocating process did not start: {line!r}")
        print(f"process {child.pid} {line}: {args.alloc_mib} MiB on GPU 0")
        in_cgroup = into_fake_container(child.pid)
        (nvml, nvml_err), nvml_ms = timed(gpu_usage.read, "nvml", run, import_nvml)
        (smi, smi_err), smi_ms = timed(gpu_usage.read, "nvidia-smi", run, import_nvml)
        raw_xml = run(gpu_usage.SMI_XML)[1]
        owner = gpu_usage.container_of_pid(child.pid)
    finally:
        if in_cgroup:
            leave_fake_container(child.pid, in_cgroup)
        child.stdin.close()
        child.wait(timeout=60)

    report.update(nvml=nvml, nvml_ms=nvml_ms, nvml_error=nvml_err, smi=smi, smi_ms=smi_ms, smi_error=smi_err)
    for name, usage, error, ms in (("NVML", nvml, nvml_err, nvml_ms), ("nvidia-smi", smi, smi_err, smi_ms)):
        if usage is None:
            problems.append(f"{name} read nothing: {error}")
            continue
        print(f"{name} ({ms} ms): driver {usage['driver']}")
        for gpu in usage["gpus"]:
            print(
                f"  GPU {gpu['index']}: {gpu['name']}, {gpu['memory_used_mib']} of {gpu['memory_total_mib']} MiB"
                f" used, {gpu['uuid']}"
            )
        for proc in usage["processes"]:
            print(f"  process {proc['pid']} on GPU {proc['gpu']} ({proc['type']}): {proc['used_mib']} MiB")
        mine = [p for p in usage["processes"] if p["pid"] == child.pid and p["gpu"] == 0]
        if not mine:
            problems.append(f"{name} does not list process {child.pid} on GPU 0")
        elif (mine[0]["used_mib"] or 0) < args.alloc_mib:
            problems.append(f"{name} gives process {child.pid} {mine[0]['used_mib']} MiB, below {args.alloc_mib}")
    if nvml and smi:
        for a, b in zip(nvml["gpus"], smi["gpus"]):
            if (a["name"], a["uuid"], a["memory_total_mib"]) != (b["name"], b["uuid"], b["memory_total_mib"]):
                problems.append(f"NVML and nvidia-smi disagree on GPU {a['index']}: {a} vs {b}")
            # both read 'used' without the driver's reserved memory; they are read a moment apart
            if abs(a["memory_used_mib"] - b["memory_used_mib"]) > 64:
                used = f"NVML {a['memory_used_mib']} MiB, nvidia-smi {b['memory_used_mib']} MiB"
                problems.append(f"GPU {a['index']} used memory: {used}")
        if nvml["driver"] != smi["driver"]:
            problems.append(f"driver version: NVML {nvml['driver']}, nvidia-smi {smi['driver']}")
    if in_cgroup:
        report["container_of_pid"] = owner
        print(f"container_of_pid({child.pid}) in the stand-in container cgroup: {owner}")
        if owner != FAKE_CONTAINER_ID:
            problems.append(f"container_of_pid gave {owner}, expected {FAKE_CONTAINER_ID}")

    report["problems"] = problems
    if args.out:
        args.out.mkdir(parents=True, exist_ok=True)
        (args.out / "nvidia-smi-q-x.xml").write_text(raw_xml)
        (args.out / "nvidia-smi-query-gpu.csv").write_text(csv)
        (args.out / "gpu_check.json").write_text(json.dumps(report, indent=2))
    for problem in problems:
        print("PROBLEM:", problem)
    print("gpu_check:", "FAILED" if problems else "all checks passed")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
