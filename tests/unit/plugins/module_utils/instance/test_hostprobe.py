"""What the plan is checked against on a host (module_utils/instance/hostprobe.py), over a fake /proc."""

from __future__ import annotations

import os

from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import hostprobe
from ansible_collections.isaacsim.fleet.tests.unit.helpers import recorded

# recorded from a test host running isaac-sim-0 (6.x) and an nginx on 49101
TCP = """  sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout inode
   0: 00000000:BFCC 00000000:0000 0A 00000000:00000000 00:00000000 00000000  1234        0 41001 1 0000000000000000 100 0 0 10 0
   1: 00000000:BFCD 00000000:0000 0A 00000000:00000000 00:00000000 00000000     0        0 41002 1 0000000000000000 100 0 0 10 0
   2: 0100007F:1F90 0100007F:A2B4 01 00000000:00000000 00:00000000 00000000     0        0 41003 1 0000000000000000 20 4 30 10 -1
"""  # noqa: E501 - /proc/net/tcp as the kernel writes it
UDP = """   sl  local_address rem_address   st tx_queue rx_queue tr tm->when retrnsmt   uid  timeout inode ref pointer drops
  100: 00000000:BB7E 00000000:0000 07 00000000:00000000 00:00000000 00000000  1234        0 41004 2 0000000000000000 0
"""  # noqa: E501
CONTAINER = "3f1c" + "0" * 60


def fake_proc(tmp_path):
    proc = tmp_path / "proc"
    (proc / "net").mkdir(parents=True)
    (proc / "net" / "tcp").write_text(TCP)
    (proc / "net" / "udp").write_text(UDP)
    (proc / "meminfo").write_text("MemTotal:       24576000 kB\nMemFree: 1 kB\n")
    for pid, comm, cgroup, inodes in (
        (100, "python3", f"12:memory:/docker/{CONTAINER}\n", [41001, 41004]),
        (200, "nginx", "0::/system.slice/nginx.service\n", [41002]),
    ):
        d = proc / str(pid)
        (d / "fd").mkdir(parents=True)
        (d / "comm").write_text(comm + "\n")
        (d / "cgroup").write_text(cgroup)
        for n, inode in enumerate(inodes):
            os.symlink(f"socket:[{inode}]", d / "fd" / str(n + 3))
    return str(proc)


def test_listening_sockets_skip_connections(tmp_path):
    socks = hostprobe.listening_sockets(fake_proc(tmp_path))
    assert sorted(sock[:2] for sock in socks) == [("tcp", 49100), ("tcp", 49101), ("udp", 47998)]


def test_ports_held_tells_ours_from_foreign(tmp_path):
    calls = []

    def ids():
        calls.append(1)
        return [CONTAINER]

    held = hostprobe.ports_held(
        {("tcp", 49100), ("tcp", 49101), ("udp", 47998), ("tcp", 8210)}, ids, fake_proc(tmp_path)
    )
    by_port = {h["port"]: h for h in held}
    assert by_port[49100]["ours"] and by_port[47998]["ours"]
    assert not by_port[49101]["ours"]
    assert by_port[49101]["process"] == "nginx (pid 200)"
    assert 8210 not in by_port
    assert calls == [1]


def test_a_port_held_by_one_of_our_host_services_is_ours(tmp_path):
    proc = fake_proc(tmp_path)
    assert hostprobe.ports_held({("tcp", 49101)}, lambda: [], proc, our_units=["nginx.service"])[0]["ours"]
    assert not hostprobe.ports_held({("tcp", 49101)}, lambda: [], proc, our_units=["x-nginx.service"])[0]["ours"]


def test_a_container_of_ours_docker_lost_is_ours_and_marked_lost(tmp_path):
    """A process in a container Docker no longer knows (not among our ids) that carries the collection's
    mark, ISAAC_SIM_INSTANCE, in its environment: left by a crashed dockerd, cleared at its unit's start;
    the plan does not refuse the deploy for it. Without the mark it stays foreign."""
    proc = fake_proc(tmp_path)
    (tmp_path / "proc" / "100" / "environ").write_text("PATH=/usr/bin\0ISAAC_SIM_INSTANCE=1\0HOME=/\0")
    [held] = hostprobe.ports_held({("tcp", 49100)}, lambda: [], proc)
    assert held["ours"] is True and held["lost"] is True
    (tmp_path / "proc" / "100" / "environ").write_text("PATH=/usr/bin\0MY_ISAAC_SIM_INSTANCE=1\0")
    [held] = hostprobe.ports_held({("tcp", 49100)}, lambda: [], proc)
    assert held["ours"] is False and "lost" not in held
    # the mark in a process outside any container (nginx's service) is no container of ours
    (tmp_path / "proc" / "200" / "environ").write_text("ISAAC_SIM_INSTANCE=1\0")
    [held] = hostprobe.ports_held({("tcp", 49101)}, lambda: [], proc)
    assert held["ours"] is False


def test_docker_is_not_asked_when_no_wanted_port_is_taken(tmp_path):
    def ids():
        raise AssertionError("docker asked for nothing")

    assert hostprobe.ports_held({("tcp", 60000)}, ids, fake_proc(tmp_path)) == []


def test_memory(tmp_path):
    assert hostprobe.memory_bytes(fake_proc(tmp_path)) == 24576000 * 1024


def test_gpu_list():
    out = "0, NVIDIA H100 80GB HBM3, 81559, 570.172.08\n1, NVIDIA L40S, 46068, 570.172.08\n"
    gpus = hostprobe.parse_gpu_list(out)
    assert gpus[1] == {"index": 1, "name": "NVIDIA L40S", "memory_total_mib": 46068, "driver": "570.172.08"}
    assert hostprobe.parse_gpu_list("No devices were found\n") == []


def test_gpu_list_recorded_on_a_real_h100():
    out = recorded("h100-nvidia-smi-query-gpu.csv")
    assert hostprobe.parse_gpu_list(out) == [
        {"index": 0, "name": "NVIDIA H100 80GB HBM3", "memory_total_mib": 81559, "driver": "580.159.04"}
    ]


def test_existing_instances(tmp_path):
    conf = tmp_path / "etc"
    wants = tmp_path / "wants"
    conf.mkdir()
    wants.mkdir()
    for n in (0, 1, 3):
        (conf / f"instance-{n}.env").write_text("")
    (conf / "instance-x.env").write_text("")
    os.symlink("/nowhere", wants / "isaac-sim@5.service")
    assert hostprobe.existing_instances(str(conf), str(wants)) == [0, 1, 3, 5]


def test_existing_companions_and_their_templates(tmp_path):
    conf, units = tmp_path / "etc", tmp_path / "units"
    conf.mkdir()
    units.mkdir()
    for name in (
        "instance-0.env",
        "instance-0.viewer.env",
        "instance-0.ros-bridge.env",
        "instance-3.viewer.env",
        "instance-1.Bad.env",
        "notes.env",
    ):
        (conf / name).write_text("")
    for name in ("isaac-sim@.service", "isaac-sim-viewer@.service", "isaac-sim-metrics.service", "isaac-sim.target"):
        (units / name).write_text("")
    assert hostprobe.existing_companions(str(conf)) == {0: ["ros-bridge", "viewer"], 3: ["viewer"]}
    assert hostprobe.companion_templates(str(units)) == ["viewer"]
