"""systemd's sandbox: each profile what its units need, and every unit the collection writes with its own."""

from __future__ import annotations

from collections import Counter

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.common import sandbox
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import firewall, plan, unit_files
from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import testrun
from ansible_collections.isaacsim.fleet.tests.unit.helpers import plan_config

PROFILES = {
    "reader": sandbox.reader(),
    "metrics": sandbox.reader(writable=["/var/lib/node-exporter"], network=False),
    "docker": sandbox.docker_client(),
    "docker-localhost": sandbox.docker_client(localhost=True),
    "firewall": sandbox.firewall(),
    "agent": sandbox.agent(),
}


def lines(profile) -> list:
    return [f"{key}={value}" for key, value in profile if value is not None]


def values(profile) -> dict:
    return {key: value for key, value in profile if value is not None}


@pytest.mark.parametrize("name", sorted(PROFILES))
def test_a_profile_sets_each_key_once_and_takes_every_capability_it_does_not_name(name):
    profile = PROFILES[name]
    # SystemCallFilter stacks (an allow list, then what it takes out of it); any other key set twice
    # would hide the first value from a reader of the unit
    twice = [k for k, n in Counter(k for k, _v in profile).items() if n > 1 and k != "SystemCallFilter"]
    assert twice == []
    v = values(profile)
    assert v["NoNewPrivileges"] == "yes" and v["ProtectSystem"] == "strict" and v["AmbientCapabilities"] == ""
    # the agent's others: test_the_agent_writes_only_the_instances_files_the_lock_and_its_own_state
    assert v["CapabilityBoundingSet"].split()[:1] == (["CAP_NET_ADMIN"] if name in ("firewall", "agent") else [])


def test_a_docker_client_reaches_docker_and_netlink_only_and_writes_only_the_run_directory():
    v = values(sandbox.docker_client())
    assert v["RestrictAddressFamilies"] == "AF_UNIX AF_NETLINK" and v["IPAddressDeny"] == "any"
    assert "IPAddressAllow" not in v and "ReadWritePaths" not in v
    # an empty home: the docker client reads no config, so no registry key either
    assert v["ProtectHome"] == "tmpfs" and v["PrivateUsers"] == "yes" and v["PrivateDevices"] == "yes"
    # the ready markers and a test run's exit files, in the directory every unit shares and keeps
    assert f"/run/{v['RuntimeDirectory']}" == layout.RUN_DIR and v["RuntimeDirectoryPreserve"] == "yes"
    # a denied system call fails instead of killing the docker client
    assert v["SystemCallErrorNumber"] == "EPERM"
    hub = values(sandbox.docker_client(localhost=True))
    assert hub["IPAddressAllow"] == "localhost" and "AF_INET" in hub["RestrictAddressFamilies"].split()


def test_the_readers_keep_the_gpus_and_the_metrics_exporter_no_network():
    reader = values(sandbox.reader())
    # nvidia-smi opens /dev/nvidia*; ProtectProc would hide the GPU processes' containers
    assert "PrivateDevices" not in reader and "ProtectProc" not in reader
    assert reader["RestrictAddressFamilies"] == "AF_UNIX AF_INET AF_INET6"
    metrics = sandbox.reader(writable=["/var/lib/node-exporter"], network=False)
    # the IP families stay (the host's address is asked of a UDP socket that sends nothing); no packet passes
    assert values(metrics)["RestrictAddressFamilies"] == "AF_UNIX AF_INET AF_INET6"
    assert values(metrics)["IPAddressDeny"] == "any" and "IPAddressDeny" not in reader
    assert [v for k, v in metrics if k == "ReadWritePaths"] == ["/var/lib/node-exporter"]


def test_the_firewall_keeps_what_loading_rules_at_boot_needs():
    v = values(sandbox.firewall())
    # in a user namespace of its own CAP_NET_ADMIN would not reach the host's tables; PrivateTmp
    # would wait for /tmp and /var mounts at early boot; the kernel loads nf_tables modules for it
    assert "PrivateUsers" not in v and "PrivateTmp" not in v and "ProtectKernelModules" not in v
    assert v["RestrictAddressFamilies"] == "AF_NETLINK"


def test_the_agent_writes_only_the_instances_files_the_lock_and_its_own_state():
    v = values(sandbox.agent("/data/isaac"))
    # a remove takes an env file out and, with the last instance, the host's reserved ports (sysctl); a
    # session's end moves its Documents aside under the data root
    assert v["ReadWritePaths"].split() == [
        layout.CONFIG_DIR,
        "/etc/sysctl.d",
        "/run",
        "/proc/sys/net/ipv4",
        "/data/isaac",
    ]
    assert v["CapabilityBoundingSet"].split() == ["CAP_NET_ADMIN", "CAP_DAC_OVERRIDE", "CAP_CHOWN", "CAP_FOWNER"]
    assert "ProtectKernelTunables" not in v and v["ProtectHome"] == "yes" and v["PrivateDevices"] == "yes"
    assert f"/var/lib/{v['StateDirectory']}" == layout.AGENT_STATE_DIR and v["StateDirectoryMode"] == "0700"
    # systemctl (D-Bus), Docker's socket, nft (netlink), and its own TLS port
    assert v["RestrictAddressFamilies"] == "AF_UNIX AF_NETLINK AF_INET AF_INET6"


def _units() -> dict:
    p = plan.build(plan_config(image="reg/isaac-sim:6.0.1", instance_count=1), {"memory_bytes": 64 * 1024**3})
    companion = {"name": "viewer", "ready_timeout": 60, "stop_timeout": 10}
    run = testrun.unit_text("r1", "check", {"restart": "no"}, ["/usr/bin/docker", "run", "--rm", "img"])
    metrics = unit_files.render_metrics_units(
        {"textfile_dir": "/var/lib/node-exporter", "gpu_source": "auto", "interval": "15s"}
    )[layout.METRICS_UNIT]
    status = {"name": "h", "address": "0.0.0.0", "port": 8290, "gpu_source": "auto"}
    return {
        "instance": (unit_files.render_unit(p["settings"], "m"), PROFILES["docker"]),
        "companion": (unit_files.render_companion_unit(companion, p["settings"], "m"), PROFILES["docker"]),
        "test run": (run, PROFILES["docker"]),
        "hub": (
            unit_files.render_hub_unit({"image": "hub:2", "dir": "/var/lib/hub"}, "m"),
            PROFILES["docker-localhost"],
        ),
        "status": (unit_files.render_status_unit(status), PROFILES["reader"]),
        "metrics": (metrics, PROFILES["metrics"]),
        "firewall": (firewall.unit("m"), PROFILES["firewall"]),
        "agent": (
            unit_files.render_agent_unit(
                {"name": "h", "port": 8291, "allow": ["10.0.0.9/32"], "soak": 0, "data_root": "/var/lib/isaac-sim"}
            ),
            PROFILES["agent"],
        ),
    }


@pytest.mark.parametrize("kind", ["instance", "companion", "test run", "hub", "status", "metrics", "firewall", "agent"])
def test_every_unit_the_collection_writes_runs_in_its_profile(kind):
    text, profile = _units()[kind]
    service = text.split("[Service]\n", 1)[1].split("\n[", 1)[0].splitlines()
    missing = [line for line in lines(profile) if line not in service]
    assert missing == []
