"""What the plan reads from a host (module_utils/instance/host_facts.py), through a scripted Probe."""

from __future__ import annotations

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerError
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import host_facts
from ansible_collections.isaacsim.fleet.tests.unit.helpers import plan_config, recorded

ADDR = '[{"ifname": "eth0", "addr_info": [{"family": "inet", "local": "10.0.0.5", "prefixlen": 24}]}]'
ROUTE = '[{"dst": "default", "gateway": "10.0.0.1", "dev": "eth0"}]'
NETWORK = {"Driver": "macvlan", "Options": {"parent": "eth0"}, "IPAM": {"Config": [{"Subnet": "10.0.0.0/24"}]}}


class Docker:
    """Docker's API as DockerSocket answers it: images by reference ({ref: Id}), our containers'
    ids, our network; down: every call raises as when the daemon does not answer."""

    def __init__(self, asked, images=None, ids=(), network=None, down=False):
        self.asked, self.images, self.ids, self.net, self.down = asked, images or {}, ids, network, down

    def _ask(self, what):
        self.asked.append(what)
        if self.down:
            raise DockerError("cannot reach the Docker daemon at /var/run/docker.sock: [Errno 111] Connection refused")

    def image(self, ref):
        self._ask(f"docker image {ref}")
        return {"Id": self.images[ref]} if ref in self.images else None

    def containers(self, name_prefix):
        self._ask(f"docker containers {name_prefix}")
        return [{"Id": i} for i in self.ids]

    def network(self, name):
        self._ask(f"docker network {name}")
        return self.net


def probe(tmp_path, installed=("docker", "systemctl", "ip", "nvidia-smi"), network=None, **docker):
    """A host with one H100, no image, nothing serving; what it was asked, in order."""
    asked = []

    def run(argv):
        asked.append(" ".join(argv))
        name = argv[0].rsplit("/", 1)[-1]
        if name == "nvidia-smi":
            return 0, recorded("h100-nvidia-smi-query-gpu.csv"), ""
        if name == "ip":
            return 0, ADDR if "addr" in argv else ROUTE, ""
        return 0, "", ""

    net = tmp_path / "net"
    (net / "eth0").mkdir(parents=True, exist_ok=True)
    found = host_facts.Probe(
        lambda name: f"/usr/bin/{name}" if name in installed else None,
        run,
        Docker(asked, network=network or NETWORK, **docker),
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
    # no socket is held on a wanted port: Docker is not asked which containers are ours
    assert [" ".join(a.split()[:3]) for a in asked] == [
        "/usr/bin/nvidia-smi --query-gpu=index,name,memory.total,driver_version --format=csv,noheader,nounits",
        "docker image nvcr.io/nvidia/isaac-sim:6.0.1",
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


def test_the_image_s_id_comes_from_docker_s_api_and_a_silent_daemon_has_no_image(tmp_path):
    found, _asked = probe(tmp_path, images={"reg/isaac-sim:6.0.0": "sha256:abc"})
    host = host_facts.facts(found, params(tmp_path, image="reg/isaac-sim:6.0.0"))
    assert host["image_present"] is True and host["image_id"] == "sha256:abc"
    # Docker installed but not answering: image.yml then says the daemon does not run
    found, asked = probe(tmp_path, images={"reg/isaac-sim:6.0.0": "sha256:abc"}, down=True)
    host = host_facts.facts(found, params(tmp_path, image="reg/isaac-sim:6.0.0", web_viewer_image="reg/viewer:1"))
    assert host["image_present"] is False and host["image_id"] is None
    assert host["companion_images_missing"] == ["reg/viewer:1"] and "docker image reg/viewer:1" in asked


def test_our_containers_are_asked_for_only_when_a_wanted_port_is_held(tmp_path, monkeypatch):
    seen = []

    def ports_held(wanted, our_container_ids, proc, our_units):
        seen.append(our_container_ids())
        return []

    monkeypatch.setattr(host_facts.hostprobe, "ports_held", ports_held)
    found, asked = probe(tmp_path, ids=["c0ffee", "f00d"])
    host_facts.facts(found, params(tmp_path))
    assert seen == [["c0ffee", "f00d"]] and "docker containers ^isaac-sim-" in asked
    found, _asked = probe(tmp_path, ids=["c0ffee"], down=True)
    seen.clear()
    host_facts.facts(found, params(tmp_path))
    assert seen == [[]]
