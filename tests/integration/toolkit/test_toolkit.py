"""The NVIDIA container toolkit role on a real systemd host with Docker.

The packages come from a signed local apt repository laid out like NVIDIA's,
and nvidia-smi is a stand-in (both test fixtures, see tests/fixtures).
"""

import json

import testbed
from testbed import sh

PIN = "1.17.8-1"
PACKAGES = [
    "nvidia-container-toolkit",
    "nvidia-container-toolkit-base",
    "libnvidia-container-tools",
    "libnvidia-container1",
]


def test_packages_are_installed_at_the_pinned_version(host):
    for pkg in PACKAGES:
        version = sh(host, f"dpkg-query -W -f '${{Version}}' {pkg}").stdout
        assert version == PIN, f"{pkg} is {version}, pinned {PIN}"
    # the repository offers a newer one: the pin, not luck, decided
    assert "1.18.0-1" in sh(host, "apt-cache madison nvidia-container-toolkit").stdout


def test_repository_is_signed_by_its_own_key(host):
    source = sh(host, "cat /etc/apt/sources.list.d/nvidia-container-toolkit.list").stdout
    assert "[signed-by=/etc/apt/keyrings/nvidia-container-toolkit.asc]" in source
    assert "/stable/deb/$(ARCH) /" in source
    assert "BEGIN PGP PUBLIC KEY BLOCK" in sh(host, "cat /etc/apt/keyrings/nvidia-container-toolkit.asc").stdout


def test_docker_knows_the_nvidia_runtime_and_keeps_other_settings(host):
    daemon = json.loads(sh(host, "cat /etc/docker/daemon.json").stdout)
    assert daemon["runtimes"]["nvidia"] == {"path": "nvidia-container-runtime", "args": []}
    assert daemon["log-opts"] == {"max-size": "10m"}
    assert "nvidia" in json.loads(sh(host, "docker info --format '{{json .Runtimes}}'").stdout)


def test_dev_char_rule_and_cdi_spec(host):
    rule = sh(host, "cat /etc/udev/rules.d/71-nvidia-dev-char.rules").stdout
    assert "nvidia-ctk system create-dev-char-symlinks --create-all" in rule
    spec = sh(host, "cat /etc/cdi/nvidia.yaml").stdout
    assert "kind: nvidia.com/gpu" in spec
    assert spec.count("- name:") == 2


def test_second_run_changes_nothing_and_restarts_nothing(host):
    """The scenario's idempotence check (molecule/toolkit runs no idempotence step): before any test
    changes the host."""
    started = testbed.unit_show(host, "docker.service")
    before = sh(host, "systemctl show docker -p ActiveEnterTimestampMonotonic").stdout
    result = testbed.run_playbook(host)
    assert result.returncode == 0, result.stdout[-3000:]
    assert testbed.changed_count(result, host) == 0
    assert sh(host, "systemctl show docker -p ActiveEnterTimestampMonotonic").stdout == before
    assert started["ActiveState"] == "active"


def test_old_driver_is_refused_before_any_change(host):
    sh(host, "echo STANDIN_DRIVER=550.54.15 > /etc/standin-nvidia-smi.conf")
    try:
        before = testbed.snapshot(host)
        result = testbed.run_playbook(host, {"nvidia_container_toolkit_version": "1.18.0-1"})
        out = result.stdout + result.stderr
        assert result.returncode != 0
        assert "NVIDIA driver 550.54.15 is older than 570.169, the minimum for Isaac Sim 5.x" in out
        assert testbed.snapshot(host) == before
        assert sh(host, "dpkg-query -W -f '${Version}' nvidia-container-toolkit").stdout == PIN
    finally:
        sh(host, "rm -f /etc/standin-nvidia-smi.conf")


def test_no_gpu_host_skips_the_role(host):
    sh(host, "echo STANDIN_GPUS=0 > /etc/standin-nvidia-smi.conf")
    try:
        result = testbed.run_playbook(
            host,
            {
                "isaac_sim_gpu_enabled": False,
                "nvidia_container_toolkit_version": "1.18.0-1",
                "toolkit_scenario_instances": False,
            },
        )
        assert result.returncode == 0, result.stdout[-3000:]
        assert testbed.changed_count(result, host) == 0
        assert "Check the NVIDIA driver" not in result.stdout
    finally:
        sh(host, "rm -f /etc/standin-nvidia-smi.conf")


def test_instances_get_their_gpu_through_dockers_device_requests(host):
    # 2 stand-in GPUs, 2 instances: round-robin puts instance i on GPU i
    for i in range(2):
        assert testbed.instance_ready(host, i)
        inspect = json.loads(sh(host, f"docker inspect isaac-sim-{i}").stdout)[0]
        assert inspect["HostConfig"]["Runtime"] == "nvidia"
        assert [r["DeviceIDs"] for r in inspect["HostConfig"]["DeviceRequests"]] == [[str(i)]]
        # set by Docker's nvidia device driver, which also ran the (stand-in) prestart hook
        init_env = sh(host, f"docker exec isaac-sim-{i} cat /proc/1/environ").stdout.split("\0")
        assert f"NVIDIA_VISIBLE_DEVICES={i}" in init_env
        assert f"ISAAC_SIM_GPU={i}\n" in sh(host, f"cat /etc/isaac-sim/instance-{i}.env").stdout


# 2 x 80 GB without a video encoder and 4 x 24 GB with one, as the stand-in driver describes them
MIXED = (
    "NVIDIA H100 80GB HBM3:81559:no:NVIDIA|NVIDIA H100 80GB HBM3:81559:no:NVIDIA|"
    "NVIDIA L4:23034:yes:NVIDIA|NVIDIA L4:23034:yes:NVIDIA|NVIDIA L4:23034:yes:NVIDIA|NVIDIA L4:23034:yes:NVIDIA"
)


def gpu_of(host, i: int) -> list:
    inspect = json.loads(sh(host, f"docker inspect isaac-sim-{i}").stdout)[0]
    return [d for r in inspect["HostConfig"]["DeviceRequests"] for d in r["DeviceIDs"]]


def test_instances_are_placed_by_gpu_memory_and_video_encoder(host):
    """Runs last (destroy follows verify): it leaves the host changed, six instances on the mixed GPUs.
    Instances going back where they ran once their GPUs change again is placement's unit test
    (tests/unit/plugins/module_utils/instance/test_placement.py)."""
    sh(host, f"printf '%s\\n' \"STANDIN_GPU_MODELS='{MIXED}'\" > /etc/standin-nvidia-smi.conf")
    # other GPUs behind the same stand-in UUIDs: what was kept of the old ones no longer holds
    sh(host, "rm -f /var/lib/isaac-sim/gpu-encoders.json /run/standin-nvidia.log")
    try:
        # refused before any change, both reasons at once: a streaming instance mapped to a GPU without an
        # encoder, and more 20 GiB streams than the encoding GPUs hold. Through deploy.yml, which plans every
        # host before any role runs: the converge would run the Docker and toolkit roles first (no change)
        before = testbed.snapshot(host)
        refused = testbed.run_playbook(
            host,
            {"isaac_sim_instance_count": 6, "isaac_sim_gpu_memory": "20g", "isaac_sim_gpu_map": {0: 1}},
            playbook="playbooks/deploy.yml",
        )
        out = " ".join((refused.stdout + refused.stderr).split())
        assert refused.returncode != 0
        assert "isaac_sim_gpu_map: instance 0 streams, and GPU 1 (NVIDIA H100 80GB HBM3) has no video encoder" in out
        assert "instance 5 needs 20480 MiB of GPU memory, and none of this host's GPUs with a video encoder" in out
        assert "GPU 0 (NVIDIA H100 80GB HBM3) without a video encoder: 81559 MiB, 522 reserved by the driver" in out
        assert testbed.snapshot(host) == before
        sh(host, "rm -f /run/standin-nvidia.log")

        # four streams on the encoding L4s (the two that ran on GPUs 0 and 1 move there), two headless
        # instances on the 80 GB GPUs, where the most memory is left (no warm run for the new GPU models:
        # nothing here is about warming, and the stand-in starts in seconds cold)
        placed = testbed.run_playbook(
            host,
            {
                "isaac_sim_instance_count": 6,
                "isaac_sim_instance_profiles": {4: "headless", 5: "headless"},
                "isaac_sim_warm_caches": False,
            },
        )
        assert placed.returncode == 0, placed.stdout[-3000:]
        testbed.all_ready(host, range(6))
        assert [gpu_of(host, i) for i in range(6)] == [["2"], ["3"], ["4"], ["5"], ["0"], ["1"]]
        encoders = json.loads(sh(host, "cat /var/lib/isaac-sim/gpu-encoders.json").stdout)
        assert encoders["driver"] == "570.172.08" and sorted(encoders["gpus"].values()) == [False] * 2 + [True] * 4
        # asked once: the stand-in driver logged one session per GPU, each encoder closed again
        log = sh(host, "cat /run/standin-nvidia.log").stdout.split()
        assert log.count("open") == 6 and log.count("destroy") == 4
    finally:
        # the planted stand-in driver's files go; the instances stay as placed (no run puts them back)
        sh(host, "rm -f /etc/standin-nvidia-smi.conf /run/standin-nvidia.log /var/lib/isaac-sim/gpu-encoders.json")
