"""The isaac_sim_plan module end to end: its commands answered as recorded, /proc and the unit
and config directories in a temporary directory, the Docker API a stand-in. The module only
reads: every command it runs is a query."""

from __future__ import annotations

import json
import os

import pytest
from ansible.module_utils import basic
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerError
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import host_facts
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_plan
from ansible_collections.isaacsim.fleet.tests.unit.helpers import ALICE, BOB, lock_files, recorded, run_module

IMAGE = "nvcr.io/nvidia/isaac-sim:6.0.1"
IMAGE_ID = "sha256:9c15" + "0" * 60
# systemctl list-units isaac-sim@*.service --state=active --plain --no-legend, two serving
SERVING = (
    "isaac-sim@0.service loaded active running Isaac Sim instance 0\n"
    "isaac-sim@1.service loaded active running Isaac Sim instance 1\n"
)
# /proc/net/tcp with a foreign process listening on 49101 (0xBFCD), inode 41002
TCP = (
    "  sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout inode\n"
    "   1: 00000000:BFCD 00000000:0000 0A 00000000:00000000 00:00000000 00000000     0        0 41002 1 0 100 0\n"
)
# read-only queries: what the module may run on a host (Docker it asks through its API; the
# encoder probe is a python child that opens and closes one encode session per GPU)
QUERIES = ("nvidia-smi", "systemctl list-units", "ip -j -4", "python")
# the encoder probe's answer for the stand-in's two GPUs (tests/fixtures/nvidia-driver): both encode
ENCODERS = json.dumps(
    {"gpus": [{"ordinal": i, "uuid": f"GPU-00000000-0000-0000-0000-00000000000{i}", "status": 0} for i in (0, 1)]}
)


@pytest.fixture()
def host(tmp_path, monkeypatch):
    """Two GPUs of 46068 MiB with an encoder (nvidia-smi -q -x as the stand-in prints it, 9220 and 512
    MiB held by processes not ours), the instance image present, two instances serving, 48 GiB;
    instances 0-5 set up earlier (env files); no socket held. Returns (args, commands, dirs)."""
    proc = tmp_path / "proc"
    (proc / "net").mkdir(parents=True)
    (proc / "meminfo").write_text("MemTotal:       50331648 kB\n")
    systemd = tmp_path / "systemd"
    (systemd / (layout.TARGET + ".wants")).mkdir(parents=True)
    (systemd / "isaac-sim-metrics.timer").write_text("[Timer]\n")
    config = tmp_path / "etc"
    config.mkdir()
    for i in range(6):
        (config / f"instance-{i}.env").write_text("")
    monkeypatch.setattr(host_facts, "PROC", str(proc))
    monkeypatch.setattr(host_facts, "SYS_NET", str(tmp_path / "sys-class-net"))
    images = {IMAGE: IMAGE_ID}
    commands = []

    def run_command(self, args, **kwargs):
        line = " ".join([args[0].rsplit("/", 1)[-1]] + list(args[1:]))
        commands.append(line)
        if line.startswith("nvidia-smi"):
            return 0, recorded("standin-nvidia-smi-q-x.xml"), ""
        if line.startswith("python") and args[1] == "-c":
            return 0, ENCODERS, ""
        if line.startswith("systemctl list-units"):
            return 0, SERVING, ""
        return 0, "", ""

    class Docker:
        """Docker's API: GET /images/REF/json answers from `images`; no container, no network of ours."""

        def image(self, ref):
            commands.append(f"GET /images/{ref}/json")
            return {"Id": images[ref]} if ref in images else None

        def containers(self, name_prefix):
            commands.append(f"GET /containers/json name={name_prefix}")
            return []

        def labelled(self, label):
            commands.append(f"GET /containers/json label={label}")
            return []

        def network(self, name):
            return None

    monkeypatch.setattr(host_facts, "DockerSocket", Docker)
    installed = {"nvidia-smi", "docker", "systemctl", "ip"}
    # where a warning goes depends on whether controller code was imported in this process
    warned = []
    monkeypatch.setattr(basic.AnsibleModule, "warn", lambda self, warning: warned.append(warning))
    monkeypatch.setattr(basic.AnsibleModule, "run_command", run_command)
    monkeypatch.setattr(
        basic.AnsibleModule,
        "get_bin_path",
        lambda self, name, *a, **kw: f"/usr/bin/{name}" if name in installed else None,
    )
    args = {
        "release": "6.x",
        "image": IMAGE,
        "instance_count": 4,
        "accept_eula": True,
        "public_address": "10.0.0.5",
        "memory_limit": "8g",
        "config_dir": str(config),
        "systemd_dir": str(systemd),
        "data_root": str(tmp_path / "data"),
        "allowed_networks": ["10.0.0.0/8"],
    }
    return args, commands, {"proc": proc, "installed": installed, "images": images, "warned": warned}


def test_a_good_configuration_is_planned_with_what_the_host_has(host, capsys):
    args, commands, dirs = host
    result = run_module(isaac_sim_plan.main, args, capsys)
    assert result["changed"] is False
    plan = result["plan"]
    assert plan["ids"] == [0, 1, 2, 3] and plan["image"] == IMAGE
    assert [i["ports"]["signal"] for i in plan["instances"]] == [49100, 49101, 49102, 49103]
    # 16 GiB each: the GPU with the most memory left first
    assert [i["gpu"] for i in plan["instances"]] == [1, 0, 1, 0]
    gpu = {
        "name": "NVIDIA Stand-in GPU",
        "memory_total_mib": 46068,
        "memory_reserved_mib": 522,
        "brand": "",
        "encoder": True,
        "encoder_why": None,
    }
    assert result["host"] == {
        "memory_bytes": 50331648 * 1024,
        "gpu_count": 2,
        "gpu_driver": "570.172.08",
        "gpu_current": {},
        "gpus": [
            dict(gpu, index=0, uuid="GPU-00000000-0000-0000-0000-000000000000", memory_used_mib=9220, others_mib=9220),
            dict(gpu, index=1, uuid="GPU-00000000-0000-0000-0000-000000000001", memory_used_mib=512, others_mib=512),
        ],
        "ports_held": [],
        "nvidia_smi": True,
        "image_present": True,
        "image_id": IMAGE_ID,
        "image_digests": [],
        "docker_answers": True,
        "images_configured": [],
        "mirror_trusted": False,
        "companion_images_missing": [],
        "companion_images_missing_named": [],
        "metrics_timer": True,
        "status_unit": False,
        "agent_unit": False,
        "hub_unit": False,
        "nft": False,
        # no host service asked about (host_services): none read
        "host_services": {},
        "serving": 2,
        # instances 2 and 3 do not run: they could start on empty caches, so the deploy asks
        "active_ids": [0, 1],
        "warm_leftovers": False,
        "cold_start_possible": True,
    }
    # instances 4 and 5 were set up before and are no longer planned
    assert result["stale_ids"] == [4, 5]
    # the plan's warnings reach the play as the module's
    assert any("isaac_sim_memory_limit" in w for w in plan["warnings"])
    assert dirs["warned"] == plan["warnings"]
    assert all(c.startswith((*QUERIES, "GET ")) for c in commands), commands


def test_a_bad_option_fails_with_the_plan_s_message_and_changes_nothing(host, capsys):
    args, commands, _dirs = host
    before = sorted(os.listdir(args["config_dir"]))
    result = run_module(isaac_sim_plan.main, dict(args, release="7.x", accept_eula=False), capsys)
    assert result["msg"].startswith("Isaac Sim configuration rejected before any change:\n- isaac_sim_release: ")
    assert result["errors"] and result["errors"][0].startswith("isaac_sim_release: '7.x' is not a release")
    assert "- " + result["errors"][-1] in result["msg"]
    assert "plan" not in result and "argument_spec" not in result
    assert sorted(os.listdir(args["config_dir"])) == before
    assert all(c.startswith((*QUERIES, "GET ")) for c in commands), commands


def test_check_mode_plans_the_same_and_runs_only_queries(host, capsys):
    args, commands, _dirs = host
    normal = run_module(isaac_sim_plan.main, args, capsys)
    checked = run_module(isaac_sim_plan.main, dict(args, _ansible_check_mode=True), capsys)
    assert checked["plan"] == normal["plan"] and checked["host"] == normal["host"]
    assert checked["changed"] is False
    assert all(c.startswith((*QUERIES, "GET ")) for c in commands), commands


def test_a_port_held_by_a_foreign_process_is_refused_naming_port_and_process(host, capsys):
    args, _commands, dirs = host
    (dirs["proc"] / "net" / "tcp").write_text(TCP)
    pid = dirs["proc"] / "200"
    (pid / "fd").mkdir(parents=True)
    (pid / "comm").write_text("nginx\n")
    (pid / "cgroup").write_text("0::/system.slice/nginx.service\n")
    os.symlink("socket:[41002]", pid / "fd" / "3")
    result = run_module(isaac_sim_plan.main, args, capsys)
    assert result["failed"] and any("49101" in e and "nginx (pid 200)" in e for e in result["errors"])
    # not checked: the port is not looked at
    again = run_module(isaac_sim_plan.main, dict(args, check_host_ports=False), capsys)
    assert not again.get("failed") and again["host"]["ports_held"] == []


def test_without_nvidia_smi_the_plan_says_so_in_words(host, capsys):
    args, _commands, dirs = host
    dirs["installed"].discard("nvidia-smi")
    result = run_module(isaac_sim_plan.main, args, capsys)
    assert result["failed"] and any(
        e.startswith("isaac_sim_gpu_enabled: true, but this host has no nvidia-smi") for e in result["errors"]
    )
    without = run_module(isaac_sim_plan.main, dict(args, gpu_enabled=False), capsys)
    assert without["host"]["nvidia_smi"] is False and without["host"]["gpus"] == []


def test_missing_images_are_listed_for_the_role_to_pull(host, capsys):
    args, _commands, dirs = host
    del dirs["images"][IMAGE]
    companions = [{"name": "bridge", "image": "reg/bridge:1"}]
    result = run_module(
        isaac_sim_plan.main,
        dict(args, web_viewer_image="reg/viewer:2", companions=companions, registry_login=True),
        capsys,
    )
    assert result["host"]["image_present"] is False and result["host"]["image_id"] is None
    assert result["host"]["companion_images_missing"] == ["reg/viewer:2", "reg/bridge:1"]
    # each named by the variable that gives it, for the pull's message where nothing may be pulled
    assert result["host"]["companion_images_missing_named"] == [
        "reg/viewer:2 (isaac_sim_web_viewer_image)",
        "reg/bridge:1 (isaac_sim_companions)",
    ]


def test_macvlan_reads_the_lan_and_a_docker_that_does_not_answer_is_an_error(host, capsys, monkeypatch):
    args, commands, _dirs = host

    class NoDocker:
        def image(self, ref):
            raise DockerError("cannot reach the Docker daemon")

        containers = labelled = network = image

    monkeypatch.setattr(host_facts, "DockerSocket", NoDocker)
    macvlan = dict(args, network_mode="macvlan", address_pool=["10.0.0.50-10.0.0.57"])
    result = run_module(isaac_sim_plan.main, macvlan, capsys)
    assert result["msg"] == "could not ask Docker for the network isaac-sim-macvlan: cannot reach the Docker daemon"
    assert "ip -j -4 addr show" in commands and "ip -j -4 route show default" in commands


@pytest.fixture()
def lock(tmp_path, monkeypatch):
    return lock_files(tmp_path / "run" / "lock", monkeypatch)


def test_with_lock_the_plan_holds_the_host_first_and_plans_nothing_while_another_run_does(host, lock, capsys):
    """playbooks/deploy.yml's one call for both: the lock as isaac_sim_lock takes it, then the plan."""
    args, _commands, _dirs = host
    alone = run_module(isaac_sim_plan.main, args, capsys)
    assert "lock" not in alone and not lock.exists()
    taken = run_module(isaac_sim_plan.main, dict(args, lock={"holder": ALICE}), capsys)
    assert taken["lock"]["acquired"] is True and json.loads(lock.read_text())["id"] == ALICE["id"]
    assert taken["plan"] == alone["plan"]
    refused = run_module(isaac_sim_plan.main, dict(args, lock={"holder": BOB, "wait": 60}), capsys)
    assert refused["lock"]["acquired"] is False and refused["lock"]["holder"]["id"] == ALICE["id"]
    assert "plan" not in refused and "failed" not in refused
    # a dry run plans against the held host all the same, and writes nothing
    looked = run_module(isaac_sim_plan.main, dict(args, lock={"holder": BOB}, _ansible_check_mode=True), capsys)
    assert looked["lock"]["acquired"] is False and looked["plan"] == alone["plan"]
    assert json.loads(lock.read_text())["id"] == ALICE["id"]
    # a plan refused after the lock was taken gives the host back at once: the run ends there
    bad = run_module(isaac_sim_plan.main, dict(args, release="7.x", lock={"holder": ALICE}), capsys)
    assert (
        bad["failed"]
        and bad["errors"]
        and bad["lock"]
        == {
            "acquired": False,
            "released": True,
            "holder": None,
            "note": "",
        }
    )
    assert not lock.exists() or json.loads(lock.read_text() or "{}").get("id") != ALICE["id"]
    # another run takes the host at once, with nobody to wait for
    assert run_module(isaac_sim_plan.main, dict(args, lock={"holder": BOB}), capsys)["lock"]["acquired"] is True


def test_a_lock_without_a_holder_is_refused_in_words(host, lock, capsys):
    args, _commands, _dirs = host
    result = run_module(isaac_sim_plan.main, dict(args, lock={"wait": 0}), capsys)
    assert result["failed"] and "holder: needs an id" in result["msg"] and "plan" not in result


def test_gather_facts_returns_setup_s_min_facts_with_a_plan_and_none_while_waiting(host, lock, capsys):
    args, _commands, _dirs = host
    assert "ansible_facts" not in run_module(isaac_sim_plan.main, args, capsys)
    planned = run_module(isaac_sim_plan.main, dict(args, gather_facts=True, lock={"holder": ALICE}), capsys)
    assert planned["plan"] and planned["ansible_facts"]["ansible_os_family"]
    # another run holds the host: no plan, and no facts gathered for it
    waiting = run_module(isaac_sim_plan.main, dict(args, gather_facts=True, lock={"holder": BOB}), capsys)
    assert "plan" not in waiting and "ansible_facts" not in waiting
