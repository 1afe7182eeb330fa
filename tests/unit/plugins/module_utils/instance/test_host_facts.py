"""What the plan reads from a host (module_utils/instance/host_facts.py), through a scripted Probe."""

from __future__ import annotations

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import host_facts
from ansible_collections.isaacsim.fleet.tests.unit.helpers import plan_config, recorded

ADDR = '[{"ifname": "eth0", "addr_info": [{"family": "inet", "local": "10.0.0.5", "prefixlen": 24}]}]'
ROUTE = '[{"dst": "default", "gateway": "10.0.0.1", "dev": "eth0"}]'
NETWORK = {"Driver": "macvlan", "Options": {"parent": "eth0"}, "IPAM": {"Config": [{"Subnet": "10.0.0.0/24"}]}}


def probe(tmp_path, installed=("docker", "systemctl", "ip", "nvidia-smi"), network=None):
    """A host with one H100, no image, nothing serving; the commands it was asked, in order."""
    asked = []

    def run(argv):
        asked.append(" ".join(argv))
        name = argv[0].rsplit("/", 1)[-1]
        if name == "nvidia-smi":
            return 0, recorded("h100-nvidia-smi-query-gpu.csv"), ""
        if name == "ip":
            return 0, ADDR if "addr" in argv else ROUTE, ""
        if argv[1:3] == ["image", "inspect"]:
            return 1, "", "No such image"
        return 0, "", ""

    net = tmp_path / "net"
    (net / "eth0").mkdir(parents=True)
    found = host_facts.Probe(
        lambda name: f"/usr/bin/{name}" if name in installed else None,
        run,
        network or (lambda name: NETWORK),
        lambda: "10.0.0.5",
        str(tmp_path / "proc"),
        str(net),
    )
    return found, asked


def params(tmp_path, **over):
    p = plan_config(
        check_host_ports=True,
        companions=[],
        profile="streaming",
        instance_profiles={},
        status_server={"enabled": False},
        hub_cache={"enabled": False},
        web_viewer_image="",
        network_mode="host",
        systemd_dir=str(tmp_path / "systemd"),
        config_dir=str(tmp_path / "etc"),
    )
    p.update(over)
    return p


def test_facts_are_read_with_one_query_each(tmp_path):
    found, asked = probe(tmp_path)
    host = host_facts.facts(found, params(tmp_path, gpu_enabled=True))
    assert host["gpu_count"] == 1 and host["gpus"][0]["memory_total_mib"] == 81559 and host["nvidia_smi"]
    assert host["image_present"] is False and host["image_id"] is None and host["serving"] == 0
    assert host["memory_bytes"] == 0 and "interfaces" not in host  # no /proc/meminfo; not macvlan
    # no socket is held on a wanted port: docker ps (which containers are ours) is not asked
    assert [" ".join(a.split()[:3]) for a in asked] == [
        "/usr/bin/nvidia-smi --query-gpu=index,name,memory.total,driver_version --format=csv,noheader,nounits",
        "/usr/bin/docker image inspect",
        "/usr/bin/systemctl list-units isaac-sim@*.service",
    ]


def test_macvlan_facts_are_the_lan_and_our_network(tmp_path):
    found, _asked = probe(tmp_path)
    host = host_facts.facts(found, params(tmp_path, network_mode="macvlan"))
    assert host["interfaces"] == ["eth0"] and host["links"] == {"eth0": [("10.0.0.5", 24)]}
    assert host["default_route"] == {"dev": "eth0", "gateway": "10.0.0.1"}
    assert host["network"]["parent"] == "eth0" and host["network"]["subnet"] == "10.0.0.0/24"


def test_a_host_without_docker_or_ip_has_no_image_and_no_lan_facts(tmp_path):
    found, asked = probe(tmp_path, installed=())
    host = host_facts.facts(found, params(tmp_path, network_mode="macvlan"))
    assert asked == [] and host["image_present"] is False and host["serving"] == 0
    assert "links" not in host and "network" not in host


def test_plan_host_returns_the_plan_and_refuses_with_every_error(tmp_path):
    found, _asked = probe(tmp_path)
    out = host_facts.plan_host(found, params(tmp_path, public_address=None, image_pull="never"))
    assert out["plan"]["ids"] == [0, 1, 2, 3] and out["stale_ids"] == [] and out["warnings"] == out["plan"]["warnings"]
    assert out["plan"]["public_address"] == "10.0.0.5"  # the default route's
    with pytest.raises(host_facts.PlanRefusedError) as exc:
        host_facts.plan_host(found, params(tmp_path, instance_count=9, accept_eula=False))
    assert exc.value.msg.startswith("Isaac Sim configuration rejected before any change:\n- ")
    assert len(exc.value.fields["errors"]) >= 2
