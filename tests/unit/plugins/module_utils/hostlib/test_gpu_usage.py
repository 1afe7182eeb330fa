"""GPU memory per process (module_utils/hostlib/gpu_usage.py): NVML, nvidia-smi's XML, and the process's container."""

from __future__ import annotations

from types import SimpleNamespace

from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import gpu_usage
from ansible_collections.isaacsim.fleet.tests.unit.helpers import no_nvml, recorded


def test_smi_xml_gives_gpus_in_index_order_with_processes():
    gpu = gpu_usage.parse_smi_xml(recorded("standin-nvidia-smi-q-x.xml"))
    assert gpu["driver"] == "570.172.08"
    assert [g["index"] for g in gpu["gpus"]] == [0, 1]
    assert gpu["gpus"][0]["memory_total_mib"] == 46068 and gpu["gpus"][0]["memory_used_mib"] == 9220
    assert {(p["gpu"], p["pid"], p["used_mib"]) for p in gpu["processes"]} == {
        (0, 4242, 9120),
        (0, 99, 100),
        (1, 777, 512),
    }


def test_smi_xml_recorded_on_a_real_h100():
    """nvidia-smi -q -x from an H100 (driver 580.159.04) while one process held 4 GiB (tests/hardware/gpu_check.py)."""
    usage = gpu_usage.parse_smi_xml(recorded("h100-nvidia-smi-q-x.xml"))
    assert usage["driver"] == "580.159.04"
    assert usage["gpus"] == [
        {
            "index": 0,
            "name": "NVIDIA H100 80GB HBM3",
            "uuid": "GPU-7c29f82e-cc0f-6e84-d164-aa52ca7577e0",
            "memory_total_mib": 81559,
            "memory_used_mib": 4715,
            "memory_reserved_mib": 480,
            "brand": "NVIDIA",
        }
    ]
    assert usage["processes"] == [{"gpu": 0, "pid": 470, "type": "C", "used_mib": 4706}]


def recorded_nvml(calls):
    """nvidia-ml-py's calls (pynvml names), answering with fixed values of the shape pynvml returns."""
    return SimpleNamespace(
        nvmlInit=lambda: calls.append("init"),
        nvmlShutdown=lambda: calls.append("shutdown"),
        nvmlSystemGetDriverVersion=lambda: b"570.172.08",
        nvmlDeviceGetCount=lambda: 1,
        nvmlDeviceGetHandleByIndex=lambda i: i,
        nvmlDeviceGetName=lambda h: "NVIDIA H100 80GB HBM3",
        nvmlDeviceGetUUID=lambda h: "GPU-abc",
        nvmlDeviceGetMemoryInfo=lambda h: SimpleNamespace(total=85520809984, used=10 * 1024**3, free=0),
        nvmlDeviceGetComputeRunningProcesses=lambda h: [
            SimpleNamespace(pid=10, usedGpuMemory=2 * 1024**3),
            SimpleNamespace(pid=11, usedGpuMemory=None),
        ],
        nvmlDeviceGetGraphicsRunningProcesses=lambda h: [SimpleNamespace(pid=10, usedGpuMemory=3 * 1024**3)],
    )


def test_nvml_path_merges_compute_and_graphics_lists():
    calls = []
    nvml = recorded_nvml(calls)
    usage, error = gpu_usage.read("auto", run=None, import_nvml=lambda: nvml)
    assert error is None and usage["source"] == "nvml" and usage["driver"] == "570.172.08"
    assert usage["gpus"] == [
        {
            "index": 0,
            "name": "NVIDIA H100 80GB HBM3",
            "uuid": "GPU-abc",
            "memory_total_mib": 81559,
            "memory_used_mib": 10240,
        }
    ]
    procs = {p["pid"]: p for p in usage["processes"]}
    assert procs[10] == {"gpu": 0, "pid": 10, "type": "C+G", "used_mib": 3072}
    assert procs[11]["used_mib"] is None
    assert calls == ["init", "shutdown"]


def test_nvml_memory_leaves_out_what_the_driver_reserves():
    """Seen on an H100 (driver 580.159.04): v1 'used' includes the reserved 480 MiB, v2 does not."""
    reserved, mib = 480 * 1024**2, 1024**2

    def memory_info(handle, version=None):
        if version is None:
            return SimpleNamespace(total=81559 * mib, used=reserved, free=81559 * mib - reserved)
        assert version == 0x02000028
        return SimpleNamespace(total=81559 * mib, reserved=reserved, used=0, free=81559 * mib - reserved)

    nvml = recorded_nvml([])
    nvml.nvmlMemory_v2 = 0x02000028
    nvml.nvmlDeviceGetMemoryInfo = memory_info
    assert gpu_usage.from_nvml(nvml)["gpus"][0]["memory_used_mib"] == 0

    def v2_missing(handle, version=None):
        if version is not None:
            raise RuntimeError("NVMLError_FunctionNotFound")
        return memory_info(handle)

    nvml.nvmlDeviceGetMemoryInfo = v2_missing
    assert gpu_usage.from_nvml(nvml)["gpus"][0]["memory_used_mib"] == 480


def test_falls_back_to_nvidia_smi_without_nvml_bindings():
    spawned = []

    def run(argv):
        spawned.append(argv)
        return 0, recorded("standin-nvidia-smi-q-x.xml"), ""

    usage, error = gpu_usage.read("auto", run, no_nvml)
    assert usage["source"] == "nvidia-smi" and error is None
    assert spawned == [["nvidia-smi", "-q", "-x"]]


def test_unreadable_xml_is_reported():
    usage, error = gpu_usage.read("nvidia-smi", lambda argv: (0, "<nvidia_smi_log><gpu>", ""), no_nvml)
    assert usage is None and error.startswith("nvidia-smi: unreadable XML")


def test_no_gpu_says_why_and_none_spawns_nothing():
    usage, error = gpu_usage.read("auto", lambda argv: (6, "No devices were found", ""), no_nvml)
    assert usage is None and "nvidia-ml-py" in error and "No devices were found" in error
    assert gpu_usage.read("none", run=None, import_nvml=None) == (None, None)
    assert gpu_usage.read("nvml", run=None, import_nvml=no_nvml)[0] is None


def test_container_of_pid_reads_cgroup_v1_and_v2(tmp_path):
    cid = "ab" * 32
    for pid, text in (
        (1, f"0::/system.slice/docker-{cid}.scope\n"),
        (2, f"12:memory:/docker/{cid}\n"),
        (3, "0::/init.scope\n"),
    ):
        (tmp_path / str(pid)).mkdir()
        (tmp_path / str(pid) / "cgroup").write_text(text)
    assert gpu_usage.container_of_pid(1, str(tmp_path)) == cid
    assert gpu_usage.container_of_pid(2, str(tmp_path)) == cid
    assert gpu_usage.container_of_pid(3, str(tmp_path)) is None
    assert gpu_usage.container_of_pid(4, str(tmp_path)) is None
