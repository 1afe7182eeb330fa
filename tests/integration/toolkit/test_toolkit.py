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
