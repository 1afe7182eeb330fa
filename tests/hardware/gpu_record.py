"""Record what a real NVIDIA GPU answers to every query the collection makes or may make.

Not part of the test suite (CI has no GPU): run it by hand on a GPU host, as root.

    python3 tests/hardware/gpu_record.py --out DIR

It writes, each as the driver printed it, for tests/unit/recorded:
  nvidia-smi-help-query-gpu.txt   the query fields this driver knows
  nvidia-smi-q.txt, nvidia-smi-q-x.xml
  nvidia-smi-query-placement.csv  the fields placement reads (memory, encoder)
  nvml.json                       each NVML call placement or status may make, with its answer
                                  or the exception it raised (class and message), per GPU
Nothing is interpreted here: the unit tests replay these answers through module_utils.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

# memory, encoder and identity: what placement by GPU memory and video encoder could read
PLACEMENT_FIELDS = (
    "index,name,uuid,pci.bus_id,memory.total,memory.reserved,memory.used,memory.free,driver_version,"
    "compute_cap,mig.mode.current,encoder.stats.sessionCount,encoder.stats.averageFps,utilization.encoder"
)


def smi(*args):
    proc = subprocess.run(["nvidia-smi", *args], capture_output=True, text=True, check=False)
    return f"# nvidia-smi {' '.join(args)}: rc {proc.returncode}\n{proc.stdout}{proc.stderr}"


def plain(value):
    """An NVML answer as JSON: ctypes structures as their fields, bytes as text."""
    if isinstance(value, bytes):
        return value.decode(errors="replace")
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    fields = getattr(value, "_fields_", None)
    if fields:
        return {field[0]: plain(getattr(value, field[0])) for field in fields}
    return repr(value)


def nvml_calls():
    import pynvml

    out = {"bindings": getattr(pynvml, "__version__", "?"), "system": {}, "gpus": []}

    def call(fn, *args, **kwargs):
        start = time.perf_counter()
        try:
            answer = {"value": plain(fn(*args, **kwargs))}
        except Exception as exc:  # NVMLError_NotSupported and the like are the answer we want
            answer = {"error": type(exc).__name__, "message": str(exc)}
        answer["ms"] = round((time.perf_counter() - start) * 1000, 2)
        return answer

    pynvml.nvmlInit()
    try:
        out["system"]["driver"] = call(pynvml.nvmlSystemGetDriverVersion)
        out["system"]["nvml_version"] = call(pynvml.nvmlSystemGetNVMLVersion)
        out["system"]["cuda_driver_version"] = call(pynvml.nvmlSystemGetCudaDriverVersion)
        out["system"]["count"] = call(pynvml.nvmlDeviceGetCount)
        queries = {
            name: getattr(pynvml, name, None)
            for name in ("NVML_ENCODER_QUERY_H264", "NVML_ENCODER_QUERY_HEVC", "NVML_ENCODER_QUERY_AV1")
        }
        for index in range(pynvml.nvmlDeviceGetCount()):
            handle = pynvml.nvmlDeviceGetHandleByIndex(index)
            gpu = {"index": index}
            for name in (
                "nvmlDeviceGetName",
                "nvmlDeviceGetUUID",
                "nvmlDeviceGetBrand",
                "nvmlDeviceGetArchitecture",
                "nvmlDeviceGetCudaComputeCapability",
                "nvmlDeviceGetMemoryInfo",
                "nvmlDeviceGetMigMode",
                "nvmlDeviceGetEncoderUtilization",
                "nvmlDeviceGetEncoderStats",
                "nvmlDeviceGetEncoderSessions",
                "nvmlDeviceGetDecoderUtilization",
                "nvmlDeviceGetJpgUtilization",
                "nvmlDeviceGetOfaUtilization",
                "nvmlDeviceGetDisplayMode",
                "nvmlDeviceGetVirtualizationMode",
                "nvmlDeviceGetPersistenceMode",
                "nvmlDeviceGetComputeMode",
                "nvmlDeviceGetMinorNumber",
            ):
                fn = getattr(pynvml, name, None)
                gpu[name] = call(fn, handle) if fn else {"error": "absent from these bindings"}
            version = getattr(pynvml, "nvmlMemory_v2", None)
            if version is not None:
                gpu["nvmlDeviceGetMemoryInfo_v2"] = call(pynvml.nvmlDeviceGetMemoryInfo, handle, version=version)
            for qname, qvalue in queries.items():
                key = f"nvmlDeviceGetEncoderCapacity({qname})"
                if qvalue is None:
                    gpu[key] = {"error": "absent from these bindings"}
                else:
                    gpu[key] = call(pynvml.nvmlDeviceGetEncoderCapacity, handle, qvalue)
            out["gpus"].append(gpu)
    finally:
        pynvml.nvmlShutdown()
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "nvidia-smi-help-query-gpu.txt").write_text(smi("--help-query-gpu"))
    (args.out / "nvidia-smi-q.txt").write_text(smi("-q"))
    (args.out / "nvidia-smi-q-x.xml").write_text(
        subprocess.run(["nvidia-smi", "-q", "-x"], capture_output=True, text=True, check=False).stdout
    )
    (args.out / "nvidia-smi-query-placement.csv").write_text(
        smi(f"--query-gpu={PLACEMENT_FIELDS}", "--format=csv,nounits")
    )
    try:
        nvml = nvml_calls()
    except Exception as exc:  # no bindings or no driver: say so in the record
        nvml = {"error": type(exc).__name__, "message": str(exc)}
    (args.out / "nvml.json").write_text(json.dumps(nvml, indent=1))
    print(json.dumps(nvml, indent=1)[:6000])
    return 0


if __name__ == "__main__":
    sys.exit(main())
