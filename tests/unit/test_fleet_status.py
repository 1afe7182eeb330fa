"""isaac_sim_info's logic on outputs recorded from a test host.

Recorded (tests/unit/recorded) from the molecule default host with four 6.x
stand-in instances, instance 3 stopped and a stray `isaac-sim-9` container
started by hand: `systemctl show` (systemd 252), the Docker API's container
and image lists (Docker 20.10, API 1.41), an env file, and a reverse JSON
journal read. The nvidia-smi XML comes from the stand-in nvidia-smi fixture,
which prints nvidia-smi's layout (no GPU was at hand to record a real one).
"""

import json
from pathlib import Path
from types import SimpleNamespace

import pytest
from ansible_collections.isaacsim.fleet.plugins.filter.systemd_env_quote import systemd_env_quote
from ansible_collections.isaacsim.fleet.plugins.module_utils import fleet_status, gpu_usage

REC = Path(__file__).parent / "recorded"
NOW = 1795354574  # `date +%s` on the host right after the recording


def recorded(name):
    return (REC / name).read_text()


def containers():
    return fleet_status.parse_containers(
        json.loads(recorded("docker-containers.json")), json.loads(recorded("docker-images.json")), NOW
    )


def env(i):
    text = recorded("instance-2.env")
    if i == 2:
        return fleet_status.parse_env_file(text)
    return fleet_status.parse_env_file(
        text.replace("49102", str(49100 + i)).replace("48000", str(47998 + i)).replace("8212", str(8210 + i))
    )


def records(**kw):
    units = fleet_status.parse_systemctl_show(recorded("systemctl-show.txt"))
    markers = {0: NOW - 200, 1: NOW - 195, 2: NOW - 190}
    args = dict(
        envs={i: env(i) for i in range(4)},
        units=units,
        containers=containers(),
        markers=markers,
        gpu=None,
        pid_containers={},
        default_address="10.9.9.9",
        now=NOW,
        monotonic_now=11900.0,
    )
    args.update(kw)
    return {r["name"]: r for r in fleet_status.build(**args)}


def test_systemctl_show_one_block_per_unit():
    units = fleet_status.parse_systemctl_show(recorded("systemctl-show.txt"))
    assert sorted(units) == [0, 1, 2, 3]
    assert units[0]["ActiveState"] == "active" and units[0]["UnitFileState"] == "enabled"
    assert units[3]["ActiveState"] == "inactive" and units[3]["SubState"] == "dead"


def test_systemctl_show_asks_once_for_configured_and_loaded_units():
    argv = fleet_status.systemctl_show_argv([0, 1, 7])
    assert argv[:2] == ["systemctl", "show"]
    assert argv[-4:] == ["isaac-sim@0.service", "isaac-sim@1.service", "isaac-sim@7.service", "isaac-sim@*.service"]
    assert "NRestarts" in argv[argv.index("-p") + 1]


def test_containers_carry_digest_state_and_uptime():
    c = containers()
    assert set(c) == {"isaac-sim-0", "isaac-sim-1", "isaac-sim-2", "isaac-sim-9"}
    zero = c["isaac-sim-0"]
    assert zero["state"] == "running" and zero["health"] == "none"
    assert zero["digest"] == "sha256:7ea27426fd569cff89afbef669e8d74092ec644c13e2c8c73cf5a0187506ebdd"
    assert zero["labelled_instance"] == 0
    assert zero["uptime_s"] == NOW - zero["started_at"] > 0


def test_ready_instance_has_urls_ports_and_limits():
    r = records()["isaac-sim-2"]
    assert r["state"] == "ready" and r["ready"] is True and r["configured"] and not r["stray"]
    assert r["ports"] == {"signal": 49102, "stream": 48000, "web_viewer": 8212}
    # the address the instance was deployed with wins over the host default
    assert r["public_address"] == "172.17.0.2"
    assert r["urls"] == {
        "signal": "172.17.0.2:49102",
        "stream": "172.17.0.2:48000/udp",
        "web_viewer": "http://172.17.0.2:8212/",
    }
    assert r["limits"] == {"memory": "1g", "shm_size": "256m"}
    assert r["enabled"] and r["restarts"] == 0 and r["release"] == "6.x"
    assert r["active_since"] == int(NOW - (11900.0 - 11695.598676))


def test_public_address_override_applies_to_every_url():
    r = records(address_override="sim-7.example.org")["isaac-sim-0"]
    assert r["urls"]["signal"] == "sim-7.example.org:49100"


def test_stopped_instance_reports_stopped_and_not_ready():
    r = records()["isaac-sim-3"]
    assert r["state"] == "stopped" and r["ready"] is False and r["container"] is None
    assert r["configured"] and r["enabled"]


def test_stray_container_is_reported():
    r = records()["isaac-sim-9"]
    assert r["stray"] and not r["configured"] and r["id"] == 9 and r["unit"] is None
    assert r["state"] == "stray-container" and r["container"]["state"] == "running"
    assert r["ready"] is False


def test_stray_unit_is_reported_but_a_loaded_inactive_one_is_not():
    units = fleet_status.parse_systemctl_show(recorded("systemctl-show.txt"))
    units[5] = {"Id": "isaac-sim@5.service", "LoadState": "loaded", "ActiveState": "failed", "SubState": "failed"}
    units[6] = {
        "Id": "isaac-sim@6.service",
        "LoadState": "loaded",
        "ActiveState": "inactive",
        "UnitFileState": "disabled",
    }
    r = records(units=units)
    assert r["isaac-sim-5"]["stray"] and r["isaac-sim-5"]["state"] == "failed"
    assert "isaac-sim-6" not in r


def test_not_ready_without_the_marker():
    r = records(markers={})["isaac-sim-0"]
    assert r["ready"] is False and r["state"] == "running"


@pytest.mark.parametrize(
    "active,sub,expected",
    [
        ("active", "running", "ready"),
        ("activating", "start-post", "starting"),
        ("activating", "auto-restart", "restarting"),
        ("failed", "failed", "failed"),
        ("deactivating", "stop-sigterm", "stopping"),
        ("inactive", "dead", "stopped"),
    ],
)
def test_state_words(active, sub, expected):
    assert fleet_status.state_of({"ActiveState": active, "SubState": sub}, None, True) == expected


def test_restart_count_comes_from_nrestarts():
    units = fleet_status.parse_systemctl_show(recorded("systemctl-show.txt"))
    units[1] = dict(units[1], NRestarts="3", ActiveState="activating", SubState="auto-restart")
    r = records(units=units)["isaac-sim-1"]
    assert r["restarts"] == 3 and r["state"] == "restarting" and r["ready"] is False


@pytest.mark.parametrize(
    "status,health",
    [
        ("Up 2 minutes (healthy)", "healthy"),
        ("Up 5 seconds (health: starting)", "starting"),
        ("Up 1 hour (unhealthy)", "unhealthy"),
        ("Exited (137) 3 seconds ago", "none"),
    ],
)
def test_health_from_status_text(status, health):
    assert fleet_status.health_of(status) == health


def test_env_file_parser_reads_back_what_the_role_quotes():
    secret = 'a$b"c`d\\e f'
    text = f"X={systemd_env_quote(secret)}\nPLAIN=1\n# comment\n"
    assert fleet_status.parse_env_file(text) == {"X": secret, "PLAIN": "1"}
    assert env(2)["ISAAC_SIM_READY_PATTERN"] == "App is loaded\\."


def test_2023_instance_gets_the_browser_client_url():
    e = dict(env(0), ISAAC_SIM_RELEASE="2023.1")
    for k in [k for k in e if k.startswith("ISAAC_SIM_PORT_")]:
        del e[k]
    e.update(ISAAC_SIM_PORT_HTTP="8211", ISAAC_SIM_PORT_WEBRTC="8011", ISAAC_SIM_PORT_NATIVE="8899")
    r = records(envs={0: e})["isaac-sim-0"]
    assert r["urls"]["webrtc_client"] == "http://172.17.0.2:8211/streaming/webrtc-client?server=172.17.0.2"


def test_gpu_memory_is_summed_per_container():
    gpu = gpu_usage.parse_smi_xml(recorded("standin-nvidia-smi-q-x.xml"))
    cid = containers()["isaac-sim-0"]["id"]
    envs = {i: env(i) for i in range(4)}
    envs[0]["ISAAC_SIM_GPU"] = "0"
    r = records(envs=envs, gpu=gpu, pid_containers={4242: cid, 99: cid, 777: None})
    assert r["isaac-sim-0"]["gpu"] == 0
    assert r["isaac-sim-0"]["gpu_memory_used_mib"] == 9120 + 100
    assert {p["pid"] for p in r["isaac-sim-0"]["gpu_processes"]} == {4242, 99}
    assert r["isaac-sim-1"]["gpu_memory_used_mib"] == 0  # GPU read, nothing of its own
    assert records()["isaac-sim-1"]["gpu_memory_used_mib"] is None  # no GPU read at all


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


def no_nvml():
    raise ImportError("No module named 'pynvml'")


def test_falls_back_to_nvidia_smi_without_nvml_bindings():
    spawned = []

    def run(argv):
        spawned.append(argv)
        return 0, recorded("standin-nvidia-smi-q-x.xml"), ""

    usage, error = gpu_usage.read("auto", run, no_nvml)
    assert usage["source"] == "nvidia-smi" and error is None
    assert spawned == [["nvidia-smi", "-q", "-x"]]


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


def test_journal_tail_keeps_the_last_lines_oldest_first_and_stops_early():
    lines = recorded("journal-reverse.jsonl").splitlines()
    tails = fleet_status.take_journal_tail(iter(lines), [3], 3)
    assert tails[3] == [
        "Error: No such container: isaac-sim-3",
        "isaac-sim@3.service: Deactivated successfully.",
        "Stopped isaac-sim@3.service - Isaac Sim instance 3.",
    ]

    def no_reading_past(limit):
        for n, line in enumerate(lines):
            if n >= limit:
                raise AssertionError("read past the lines it needed")
            yield line

    assert len(fleet_status.take_journal_tail(no_reading_past(2), [3], 2)[3]) == 2


def test_journal_tail_of_a_quiet_unit_is_empty():
    tails = fleet_status.take_journal_tail(iter(recorded("journal-reverse.jsonl").splitlines()), [2, 3], 2)
    assert tails[2] == [] and len(tails[3]) == 2


class CountingDocker:
    def __init__(self):
        self.calls = 0

    def containers(self, prefix):
        self.calls += 1
        return json.loads(recorded("docker-containers.json"))

    def images(self):
        self.calls += 1
        return json.loads(recorded("docker-images.json"))


@pytest.mark.parametrize("n", [1, 4, 8])
def test_cost_does_not_grow_with_instances(tmp_path, n):
    config = tmp_path / "etc"
    config.mkdir()
    for i in range(n):
        (config / f"instance-{i}.env").write_text(recorded("instance-2.env"))
    spawned = []

    def run(argv):
        spawned.append(argv[0])
        if argv[0] == "systemctl":
            return 0, recorded("systemctl-show.txt"), ""
        return 0, recorded("standin-nvidia-smi-q-x.xml"), ""

    def stream(argv, consume):
        spawned.append(argv[0])
        return consume(iter(recorded("journal-reverse.jsonl").splitlines()))

    docker = CountingDocker()
    result = fleet_status.gather(
        run, stream, docker, no_nvml, config_dir=str(config), run_dir=str(tmp_path / "run"), log_lines=5
    )
    assert len([r for r in result["instances"] if r["configured"]]) == n
    assert sorted(spawned) == ["journalctl", "nvidia-smi", "systemctl"]
    assert docker.calls == 2
    assert result["deployed"] and result["summary"]["configured"] == n


def test_a_host_without_the_collection_is_not_deployed(tmp_path):
    result = fleet_status.gather(
        lambda argv: (0, "", ""),
        None,
        CountingDocker(),
        no_nvml,
        config_dir=str(tmp_path),
        run_dir=str(tmp_path),
        unit_path=str(tmp_path / "none"),
        gpu_source="none",
    )
    assert result["deployed"] is False
    assert [r["name"] for r in result["instances"]] == ["isaac-sim-0", "isaac-sim-1", "isaac-sim-2", "isaac-sim-9"]
    assert all(r["stray"] for r in result["instances"])


def test_default_ipv4_is_an_address():
    parts = fleet_status.default_ipv4().split(".")
    assert len(parts) == 4 and all(p.isdigit() for p in parts)
