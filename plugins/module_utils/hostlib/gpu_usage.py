# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""GPUs and the memory each process holds on them: NVML first, nvidia-smi after.

Both paths return the same shape:
  {"source": "nvml" | "nvidia-smi", "driver": str,
   "gpus": [{index, name, uuid, memory_total_mib, memory_used_mib}, nvidia-smi's also
            memory_reserved_mib and brand],
   "processes": [{gpu, pid, type, used_mib}]}
A process's container is found from /proc/PID/cgroup, with no process spawned.
"""

from __future__ import annotations

import os
import re

SMI_XML = ["nvidia-smi", "-q", "-x"]
_MIB = 1024 * 1024


def _text(value):
    return value.decode() if isinstance(value, bytes) else str(value)


def _memory_info(nvml, handle):
    """Memory with the driver's reserved part left out of 'used', as nvidia-smi shows it.

    The v1 call counts reserved memory as used: on an idle H100 (driver 580) it said
    480 MiB used where nvidia-smi said 0. Drivers or bindings without v2 get v1.
    """
    version = getattr(nvml, "nvmlMemory_v2", None)
    if version is not None:
        try:
            return nvml.nvmlDeviceGetMemoryInfo(handle, version=version)
        except Exception:  # NVMLError_FunctionNotFound on drivers older than the v2 call
            pass
    return nvml.nvmlDeviceGetMemoryInfo(handle)


def from_nvml(nvml) -> dict:
    """Read through an initialised pynvml (nvidia-ml-py) module."""
    gpus, procs = [], {}
    for index in range(nvml.nvmlDeviceGetCount()):
        handle = nvml.nvmlDeviceGetHandleByIndex(index)
        mem = _memory_info(nvml, handle)
        gpus.append(
            {
                "index": index,
                "name": _text(nvml.nvmlDeviceGetName(handle)),
                "uuid": _text(nvml.nvmlDeviceGetUUID(handle)),
                "memory_total_mib": int(mem.total // _MIB),
                "memory_used_mib": int(mem.used // _MIB),
            }
        )
        # Isaac Sim renders (graphics) and simulates (compute): a process may be in both lists
        for kind, getter in (
            ("C", nvml.nvmlDeviceGetComputeRunningProcesses),
            ("G", nvml.nvmlDeviceGetGraphicsRunningProcesses),
        ):
            for proc in getter(handle):
                used = getattr(proc, "usedGpuMemory", None)
                used_mib = None if used is None else int(used // _MIB)
                key = (index, int(proc.pid))
                if key in procs:
                    old = procs[key]
                    old["type"] = "C+G" if old["type"] != kind else kind
                    old["used_mib"] = max(v for v in (old["used_mib"], used_mib, 0) if v is not None)
                else:
                    procs[key] = {"gpu": index, "pid": int(proc.pid), "type": kind, "used_mib": used_mib}
    return {
        "source": "nvml",
        "driver": _text(nvml.nvmlSystemGetDriverVersion()),
        "gpus": gpus,
        "processes": list(procs.values()),
    }


def _mib(text):
    match = re.match(r"\s*(\d+)", text or "")
    return int(match.group(1)) if match else None


def parse_smi_xml(text: str) -> dict:
    """Parse `nvidia-smi -q -x`: GPUs in index order, and every process on each. ParseError (a
    SyntaxError) for text that is not XML."""
    # imported here: a host without nvidia-smi (or with NVML) never pays for the XML parser
    import xml.etree.ElementTree as ET

    root = ET.fromstring(text)
    gpus, procs = [], []
    for index, gpu in enumerate(root.findall("gpu")):
        gpus.append(
            {
                "index": index,
                "name": gpu.findtext("product_name", ""),
                "uuid": gpu.findtext("uuid", ""),
                "memory_total_mib": _mib(gpu.findtext("fb_memory_usage/total")),
                "memory_used_mib": _mib(gpu.findtext("fb_memory_usage/used")),
                # what the driver keeps for itself (drivers before 525 have no such line: 0)
                "memory_reserved_mib": _mib(gpu.findtext("fb_memory_usage/reserved")) or 0,
                # GeForce, Quadro, NVIDIA, ...: consumer cards limit concurrent encode sessions
                "brand": gpu.findtext("product_brand", ""),
            }
        )
        for proc in gpu.findall("processes/process_info"):
            pid = proc.findtext("pid", "")
            if pid.isdigit():
                procs.append(
                    {
                        "gpu": index,
                        "pid": int(pid),
                        "type": proc.findtext("type", ""),
                        "used_mib": _mib(proc.findtext("used_memory")),
                    }
                )
    return {"source": "nvidia-smi", "driver": root.findtext("driver_version", ""), "gpus": gpus, "processes": procs}


def count_on(module) -> tuple:
    """(GPUs of the host a module runs on, why none when there are none): NVML, else nvidia-smi."""

    def run(argv):
        path = module.get_bin_path(argv[0])
        return module.run_command([path] + argv[1:]) if path else (127, "", f"{argv[0]} is not installed")

    found, why = read("auto", run)
    return len((found or {}).get("gpus") or []), why


def import_nvml():
    """The NVML bindings (nvidia-ml-py), where the host has them; ImportError where not."""
    import pynvml

    return pynvml


def read(source, run, import_nvml=import_nvml):
    """(usage or None, error or None), from the source asked for ("auto", "nvml", "nvidia-smi", "none").

    run(argv) -> (rc, out, err) spawns nvidia-smi; import_nvml() returns the
    pynvml module or raises ImportError. "auto" takes NVML when the Python
    bindings load and the driver answers, else nvidia-smi, else no GPU.
    """
    if source == "none":
        return None, None
    errors = []
    if source in ("auto", "nvml"):
        try:
            nvml = import_nvml()
            nvml.nvmlInit()
            try:
                return from_nvml(nvml), None
            finally:
                nvml.nvmlShutdown()
        except ImportError:
            errors.append("NVML: the nvidia-ml-py bindings are not installed")
        except Exception as exc:  # pynvml raises NVMLError_* for a missing driver or GPU
            errors.append(f"NVML: {exc}")
        if source == "nvml":
            return None, "; ".join(errors)
    rc, out, err = run(SMI_XML)
    if rc == 0 and out.strip():
        try:
            return parse_smi_xml(out), None
        except SyntaxError as exc:  # ElementTree's ParseError
            errors.append(f"nvidia-smi: unreadable XML ({exc})")
    else:
        errors.append(f"nvidia-smi: {(err or out).strip() or 'exit ' + str(rc)}")
    # no GPU is a normal state for a host without one; only say why
    return None, "; ".join(errors)


_CONTAINER_ID = re.compile(r"[0-9a-f]{64}")


def container_of_pid(pid: int, proc="/proc"):
    """The 64-hex container id in the process's cgroup path, else None."""
    try:
        with open(os.path.join(proc, str(pid), "cgroup")) as fh:
            match = _CONTAINER_ID.search(fh.read())
    except OSError:
        return None
    return match.group(0) if match else None
