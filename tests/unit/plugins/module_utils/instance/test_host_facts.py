"""What the plan reads from a host (module_utils/instance/host_facts.py), through a scripted Probe."""

from __future__ import annotations

import json

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import host_service
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerError
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import host_facts
from ansible_collections.isaacsim.fleet.tests.unit.helpers import plan_config, recorded

ADDR = '[{"ifname": "eth0", "addr_info": [{"family": "inet", "local": "10.0.0.5", "prefixlen": 24}]}]'
ROUTE = '[{"dst": "default", "gateway": "10.0.0.1", "dev": "eth0"}]'
NETWORK = {"Driver": "macvlan", "Options": {"parent": "eth0"}, "IPAM": {"Config": [{"Subnet": "10.0.0.0/24"}]}}


class Docker:
    """Docker's API as DockerSocket answers it: images by reference ({ref: Id}), our containers'
    ids, our network; down: every call raises as when the daemon does not answer."""

    def __init__(self, asked, images=None, ids=(), network=None, down=False, warm_runs=()):
        self.asked, self.images, self.ids, self.net, self.down = asked, images or {}, ids, network, down
        self.warm_runs = warm_runs

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

    def labelled(self, label):
        self._ask(f"docker labelled {label}")
        return [{"Id": i} for i in self.warm_runs]

    def network(self, name):
        self._ask(f"docker network {name}")
        return self.net


H100_UUID = "GPU-3a4bf3b5-f6d5-6f6e-6ea6-9e95c4b58413"
PYTHON = "/usr/bin/python3"


def probe(tmp_path, installed=("docker", "systemctl", "ip", "nvidia-smi"), network=None, check_mode=False, **docker):
    """A host with one H100 (nvidia-smi -q -x and the encoder probe as recorded on it, a process
    holding 4706 MiB), no image, nothing serving; what it was asked, in order."""
    asked = []

    def run(argv):
        asked.append(" ".join(argv))
        name = argv[0].rsplit("/", 1)[-1]
        if name == "nvidia-smi":
            return 0, recorded("h100-placement-nvidia-smi-q-x.xml"), ""
        if argv[0] == PYTHON:
            return 0, recorded("h100-nvenc-probe.json"), ""
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
        PYTHON,
        check_mode,
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
    host = host_facts.facts(found, params(tmp_path, gpu_enabled=True, data_root=str(tmp_path)))
    assert host["gpus"] == [
        {
            "index": 0,
            "name": "NVIDIA H100 80GB HBM3",
            "uuid": H100_UUID,
            "memory_total_mib": 81559,
            "memory_used_mib": 4715,
            "memory_reserved_mib": 480,
            "brand": "NVIDIA",
            # the recorded process is in no container of ours: its memory is not the plan's
            "others_mib": 4706,
            "encoder": False,
            "encoder_why": None,
        }
    ]
    assert host["gpu_count"] == 1 and host["nvidia_smi"] and host["gpu_driver"] == "580.159.04"
    assert host["image_present"] is False and host["image_id"] is None and host["serving"] == 0
    assert host["memory_bytes"] == 0 and "interfaces" not in host  # no /proc/meminfo; not macvlan
    # Docker is asked for our containers because a GPU process runs; no socket is held on a wanted port
    assert [" ".join(a.split()[:3]) for a in asked] == [
        "/usr/bin/nvidia-smi -q -x",
        "docker containers ^isaac-sim-",
        f"{PYTHON} -c import",
        "docker image nvcr.io/nvidia/isaac-sim:6.0.1",
        "/usr/bin/systemctl list-units isaac-sim@*.service",
        "docker labelled org.isaacsim.fleet.warm",
    ]


def test_a_process_in_one_of_our_containers_leaves_its_memory_to_the_plan(tmp_path):
    ours = "15aac51a" * 8
    (tmp_path / "proc" / "586").mkdir(parents=True)
    (tmp_path / "proc" / "586" / "cgroup").write_text(f"0::/system.slice/docker-{ours}.scope\n")
    found, _asked = probe(tmp_path, ids=[ours])
    host = host_facts.facts(found, params(tmp_path, gpu_enabled=True, data_root=str(tmp_path)))
    assert host["gpus"][0]["others_mib"] == 0
    found, _asked = probe(tmp_path, ids=["c0ffee"])
    assert host_facts.facts(found, params(tmp_path, gpu_enabled=True))["gpus"][0]["others_mib"] == 4706


def test_where_each_instance_runs_now_is_read_from_its_env_file(tmp_path):
    (tmp_path / "etc").mkdir()
    (tmp_path / "etc" / "instance-0.env").write_text("ISAAC_SIM_GPU=0\n")
    (tmp_path / "etc" / "instance-3.env").write_text("ISAAC_SIM_GPU=1\n")
    (tmp_path / "etc" / "instance-4.env").write_text("ISAAC_SIM_GPU=\n")
    found, _asked = probe(tmp_path)
    host = host_facts.facts(found, params(tmp_path, gpu_enabled=True, profile="headless"))
    assert host["gpu_current"] == {0: 0, 3: 1}


def test_the_encoder_is_asked_once_per_driver_and_only_for_streams(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    cache = data / host_facts.ENCODER_CACHE
    p = params(tmp_path, gpu_enabled=True, data_root=str(data))

    def read(check_mode=False):
        found, asked = probe(tmp_path, check_mode=check_mode)
        host = host_facts.facts(found, p)
        host_facts.keep_encoders(found, p, host)
        return host, any(a.startswith(PYTHON) for a in asked)

    # check mode asks but keeps nothing
    host, asked = read(check_mode=True)
    assert host["gpus"][0]["encoder"] is False and asked and not cache.exists()
    host, asked = read()
    assert json.loads(cache.read_text()) == {"driver": "580.159.04", "gpus": {H100_UUID: False}}
    # kept: the next plan does not ask the driver again
    host, asked = read()
    assert host["gpus"][0]["encoder"] is False and not asked
    # another driver: asked again
    cache.write_text(json.dumps({"driver": "570.1", "gpus": {H100_UUID: True}}))
    host, asked = read()
    assert host["gpus"][0]["encoder"] is False and asked
    # headless instances only: no encoder is needed, none is asked for
    found, asked = probe(tmp_path)
    host = host_facts.facts(found, params(tmp_path, gpu_enabled=True, data_root=str(data), profile="headless"))
    assert host["gpus"][0]["encoder"] is None and not any(a.startswith(PYTHON) for a in asked)


def test_a_refused_plan_keeps_nothing(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    found, _asked = probe(tmp_path)
    with pytest.raises(host_facts.PlanRefusedError):
        host_facts.plan_host(found, params(tmp_path, gpu_enabled=True, data_root=str(data), image_pull="never"))
    assert list(data.iterdir()) == []


def test_an_encoder_probe_that_cannot_ask_is_said_and_not_kept(tmp_path, monkeypatch):
    data = tmp_path / "data"
    data.mkdir()
    found, _asked = probe(tmp_path)
    monkeypatch.setattr(
        found,
        "run",
        lambda argv: (0, recorded("h100-placement-nvidia-smi-q-x.xml"), "")
        if "nvidia-smi" in argv[0]
        else (
            0,
            json.dumps(
                {"gpus": [], "error": "libnvidia-encode.so.1 (the driver's encode library) could not be loaded"}
            ),
            "",
        ),
    )
    p = params(tmp_path, gpu_enabled=True, data_root=str(data))
    host = host_facts.facts(found, p)
    host_facts.keep_encoders(found, p, host)
    gpu = host["gpus"][0]
    assert gpu["encoder"] is None and "libnvidia-encode.so.1" in gpu["encoder_why"]
    assert not (data / host_facts.ENCODER_CACHE).exists()


def test_streaming_on_the_recorded_h100_is_refused_and_headless_is_placed(tmp_path):
    found, _asked = probe(tmp_path)
    with pytest.raises(host_facts.PlanRefusedError) as exc:
        host_facts.plan_host(found, params(tmp_path, gpu_enabled=True, image_pull="never", instance_count=2))
    assert "instances 0, 1 stream, and no GPU of this host has a video encoder (NVIDIA H100 80GB HBM3" in exc.value.msg
    out = host_facts.plan_host(
        found, params(tmp_path, gpu_enabled=True, image_pull="never", profile="headless", instance_count=4)
    )
    assert [i["gpu"] for i in out["plan"]["instances"]] == [0, 0, 0, 0]


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


def test_a_mirror_is_asked_through_a_host_only_once_its_docker_trusts_it(tmp_path, monkeypatch):
    monkeypatch.setattr(host_facts, "CERTS_D", str(tmp_path / "certs.d"))
    found, _asked = probe(tmp_path)
    assert host_facts.facts(found, params(tmp_path, registry_mirror="m.lab:5443"))["mirror_trusted"] is False
    (tmp_path / "certs.d" / "m.lab:5443").mkdir(parents=True)
    (tmp_path / "certs.d" / "m.lab:5443" / "ca.crt").write_text("PEM")
    assert host_facts.facts(found, params(tmp_path, registry_mirror="m.lab:5443"))["mirror_trusted"] is True
    assert host_facts.facts(found, params(tmp_path))["mirror_trusted"] is False


ACTIVE = "isaac-sim@0.service loaded active running Isaac Sim instance 0\nisaac-sim@2.service loaded active running x\n"


def units_probe(tmp_path, listed=ACTIVE, rc=0, **docker):
    found, asked = probe(tmp_path, installed=("docker", "systemctl"), **docker)
    plain = found.run
    found.run = lambda argv: (rc, listed, "") if "list-units" in argv else plain(argv)
    return found, asked


@pytest.mark.parametrize(
    ("listed", "rc", "ids", "active", "possible"),
    [
        # every instance of the plan runs: none could start on empty caches
        (ACTIVE, 0, [0, 2], [0, 2], False),
        # instance 1 does not run: it could
        (ACTIVE, 0, [0, 1, 2], [0, 2], True),
        # a scale-down: the instances kept all run
        (ACTIVE, 0, [0], [0, 2], False),
        # systemd did not answer: it cannot be told, so the deploy asks
        ("", 1, [0, 2], None, True),
    ],
)
def test_which_instances_run_tells_whether_one_could_start_on_empty_caches(tmp_path, listed, rc, ids, active, possible):
    found, _asked = units_probe(tmp_path, listed, rc)
    host = host_facts.facts(found, params(tmp_path, data_root=str(tmp_path)))
    assert host["active_ids"] == active and host["serving"] == len(active or [])
    assert host["warm_leftovers"] is False
    assert host_facts.cold_start_possible(ids, host) is possible


@pytest.mark.parametrize(
    ("left", "docker", "leftovers"),
    [
        # a warm run's container a killed deploy left, which the warm probe removes
        ([], {"warm_runs": ["c0ffee"]}, True),
        # its scratch directory or a partly written archive
        ([".k1.abc/"], {}, True),
        (["k1.tar.partial"], {}, True),
        # an archive kept is no leftover, nor a file of the user's whose name starts with a dot
        (["k1.tar", ".keep"], {}, False),
        # Docker does not answer: cannot be told
        ([], {"down": True}, True),
    ],
)
def test_what_a_killed_warm_run_left_makes_the_deploy_ask(tmp_path, left, docker, leftovers):
    store = tmp_path / "warm-caches"
    store.mkdir()
    for name in left:
        (store / name.rstrip("/")).mkdir() if name.endswith("/") else (store / name).write_text("x")
    found, _asked = units_probe(tmp_path, **docker)
    host = host_facts.facts(found, params(tmp_path, data_root=str(tmp_path)))
    assert host["warm_leftovers"] is leftovers
    assert host_facts.cold_start_possible([0, 2], host) is leftovers


def test_the_host_services_asked_about_are_read_with_one_systemctl_call(tmp_path):
    """Each host service's unit state (one `systemctl show` for all) and its files' digests, for the
    deploy to leave out a host service's module call where nothing would change."""
    unit = tmp_path / "isaac-sim-status.service"
    unit.write_text("[Unit]\n")
    found, _asked = probe(tmp_path, installed=("systemctl",))
    plain = found.run
    calls = []
    shown = (
        "Id=isaac-sim-metrics.timer\nActiveState=inactive\nUnitFileState=\n\n"
        "Id=isaac-sim-status.service\nActiveState=active\nUnitFileState=enabled\n"
    )
    found.run = lambda argv: (calls.append(argv), (0, shown, ""))[1] if "show" in argv else plain(argv)
    wanted = {
        "isaac-sim-status.service": {"files": [str(unit)]},
        "isaac-sim-metrics.timer": {"files": [str(tmp_path / "none")], "directories": [str(tmp_path)]},
    }
    host = host_facts.facts(found, params(tmp_path, data_root=str(tmp_path), host_services=wanted))
    status, metrics = (
        host["host_services"]["isaac-sim-status.service"],
        host["host_services"]["isaac-sim-metrics.timer"],
    )
    assert (status["ActiveState"], status["UnitFileState"]) == ("active", "enabled")
    assert status["files"][str(unit)][0] == host_service.digest("[Unit]\n")
    assert metrics["ActiveState"] == "inactive" and metrics["files"] == {str(tmp_path / "none"): None}
    assert metrics["directories"][str(tmp_path)] is not None
    assert len(calls) == 1
    # not asked: nothing read, no call
    assert host_facts.facts(found, params(tmp_path, data_root=str(tmp_path)))["host_services"] == {}


def test_host_services_are_not_in_place_when_systemd_does_not_answer(tmp_path):
    found, _asked = probe(tmp_path, installed=("systemctl",))
    found.run = lambda argv: (1, "", "Failed to connect to bus")
    wanted = {"isaac-sim-status.service": {"files": []}}
    host = host_facts.facts(found, params(tmp_path, data_root=str(tmp_path), host_services=wanted))
    assert host["host_services"]["isaac-sim-status.service"]["ActiveState"] == ""
    assert (
        host_service.in_place({"files": {}, "state": "started"}, host["host_services"]["isaac-sim-status.service"])
        is False
    )
