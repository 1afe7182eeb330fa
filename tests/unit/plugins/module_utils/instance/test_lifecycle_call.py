"""One call of the lifecycle module (module_utils/instance/lifecycle_call.py) on the scripted host:
the instances' macvlan network, created before the first instance changes and removed once no
instance wants it, and the failures that name what to fix."""

from __future__ import annotations

import os

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerError
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import lifecycle_call, network, plan
from ansible_collections.isaacsim.fleet.tests.unit.helpers import plan_config
from ansible_collections.isaacsim.fleet.tests.unit.plugins.module_utils.instance.test_lifecycle import (
    NEVER,
    OLD,
    ScriptedHost,
)

LAN = {"mode": "macvlan", "driver": "macvlan", "parent": "eth0", "subnet": "10.0.0.0/24", "gateway": "10.0.0.1"}
RM = " ".join(network.remove_argv())


def ours(containers=None, subnet="10.0.0.0/24"):
    """Docker's answer for our network, with these containers on it."""
    return {
        "Driver": "macvlan",
        "Options": {"parent": "eth0"},
        "IPAM": {"Config": [{"Subnet": subnet, "Gateway": "10.0.0.1"}]},
        "Labels": {layout.LABEL_NETWORK: "macvlan"},
        "Containers": {
            f"id{n}": {"Name": name, "IPv4Address": "10.0.0.50/24"} for n, name in enumerate(containers or [])
        },
    }


def params(tmp_path, **over) -> dict:
    """The module's parameters with its defaults: apply a plan of four 6.x instances."""
    built = plan.build(plan_config(data_root=str(tmp_path / "data"), image="reg/isaac-sim:6.0.1"), {})
    built.update(uid=os.getuid(), gid=os.getgid())
    p = {
        "action": "apply",
        "ids": [],
        "plan": built,
        "image_id": "unknown",
        "secret_env": {},
        "scripts": {name: "#!/bin/sh\n" for name in (*layout.SCRIPTS, *layout.POLICY_LIB)},
        "managed": "managed",
        "soak_seconds": 0,
        "defer_running": False,
        "remove_others": True,
        "purge": False,
        "data_root": str(tmp_path / "data"),
        "controller_run": "",
    }
    p.update(over)
    return p


def scripted(n=4, running=True, net=None, fails=None):
    """A scripted host whose Docker answers `net` for our network (None: Docker not reachable)
    and whose `docker network` commands fail with `fails`."""
    h = ScriptedHost(n, running=running)

    def answer(name):
        if net is None:
            raise DockerError("cannot reach the Docker daemon")
        return net

    h.host.network = answer
    run = h.host.run

    def run_docker(argv):
        if argv[:2] == ["docker", "network"]:
            h.log.append(" ".join(argv))
            return (1, "", fails) if fails else (0, "", "")
        return run(argv)

    h.host.run = run_docker
    return h


def test_removing_the_last_instance_removes_our_network_once_nobody_is_on_it(tmp_path):
    h = scripted(1, net=ours())
    out = lifecycle_call.call(h.host, params(tmp_path, action="remove", ids=[0]))
    assert out["network"] == "remove" and RM in h.log and out["changed"] is True


def test_the_network_is_kept_while_a_container_or_an_instance_s_env_file_wants_it(tmp_path):
    h = scripted(1, net=ours(["someone-else"]))
    assert lifecycle_call.call(h.host, params(tmp_path, action="remove", ids=[0]))["network"] == "kept"
    h = scripted(2, net=ours())
    h.files[layout.env_file(1)] = (OLD + f"{layout.K_ADDRESS}=10.0.0.51\n", 0o644)
    out = lifecycle_call.call(h.host, params(tmp_path, action="remove", ids=[0]))
    assert out["network"] == "kept" and RM not in h.log


def test_a_network_that_cannot_be_removed_is_an_error_naming_it(tmp_path):
    h = scripted(1, net=ours(), fails="network isaac-sim-macvlan is busy\n")
    with pytest.raises(lifecycle_call.LifecycleError) as exc:
        lifecycle_call.call(h.host, params(tmp_path, action="remove", ids=[0]))
    assert exc.value.msg == "could not remove the network isaac-sim-macvlan: network isaac-sim-macvlan is busy"


def test_apply_needs_docker_to_answer_when_the_instances_need_the_network(tmp_path):
    p = params(tmp_path)
    p["plan"]["network"] = dict(LAN)
    with pytest.raises(lifecycle_call.LifecycleError) as exc:
        lifecycle_call.call(scripted(net=None).host, p)
    assert exc.value.msg == "could not ask Docker for the network isaac-sim-macvlan: cannot reach the Docker daemon"
    # on the host's network, no Docker is no network
    out = lifecycle_call.call(scripted(running=False, net=None).host, params(tmp_path))
    assert out["network"] is None and out["changed"] is True


def test_a_network_that_cannot_be_created_stops_the_apply_before_any_instance_file(tmp_path):
    h = scripted(4, running=False, net={}, fails="parent eth0 does not exist")
    p = params(tmp_path)
    p["plan"]["network"] = dict(LAN)
    with pytest.raises(lifecycle_call.LifecycleError) as exc:
        lifecycle_call.call(h.host, p)
    assert exc.value.msg == (
        "could not create the network isaac-sim-macvlan (eth0, 10.0.0.0/24): parent eth0 does not exist; "
        "nothing else was changed"
    )
    assert not any(path.startswith(layout.CONFIG_DIR) for path in h.files) and h.commands("start") == []


def test_a_network_in_use_that_differs_from_the_plan_changes_nothing(tmp_path):
    h = scripted(4, net=ours(["isaac-sim-0"], subnet="10.1.0.0/24"))
    p = params(tmp_path)
    p["plan"]["network"] = dict(LAN)
    with pytest.raises(lifecycle_call.LifecycleError) as exc:
        lifecycle_call.call(h.host, p)
    assert exc.value.msg.startswith("the network isaac-sim-macvlan differs from the plan's and is in use")
    assert h.files[layout.env_file(0)][0] == OLD and [x for x in h.log if x.startswith("docker network")] == []


def test_a_created_network_is_reported_and_check_mode_only_says_it(tmp_path):
    p = params(tmp_path)
    p["plan"]["network"] = dict(LAN)
    h = scripted(4, running=False, net={})
    checked = lifecycle_call.call(h.host, p, check=True)
    assert checked["network"] == "create" and [x for x in h.log if x.startswith("docker network")] == []
    out = lifecycle_call.call(h.host, p)
    assert out["network"] == "create" and h.log.count(" ".join(network.create_argv(LAN))) == 1


def never_ready(tmp_path, count: int) -> dict:
    """The module's parameters for a first deploy of `count` instances whose image never gets ready."""
    built = plan.build(
        plan_config(instance_count=count, data_root=str(tmp_path / "data"), image="reg/isaac-sim:never-ready"), {}
    )
    built.update(uid=os.getuid(), gid=os.getgid())
    return params(tmp_path, plan=built)


STOPPED = "it was stopped (there are no earlier settings to go back to)"


def gate(i: int) -> str:
    """The scripted gate's reason for instance i."""
    return f"isaac-sim-{i} was not ready within 20 s (last lines: loading scene)"


def test_a_new_instance_that_does_not_start_fails_the_call_naming_it_as_before(tmp_path):
    with pytest.raises(lifecycle_call.LifecycleError) as exc:
        lifecycle_call.call(scripted(1, running=False).host, never_ready(tmp_path, 1))
    assert exc.value.msg == f"isaac-sim-0: {gate(0)}; {STOPPED}"
    fields = exc.value.fields
    assert fields["failed_instance"]["id"] == 0 and fields["failed_instances"] == [fields["failed_instance"]]


def test_every_new_instance_that_does_not_start_is_named_in_the_failure(tmp_path):
    h = scripted(3, running=False)
    with pytest.raises(lifecycle_call.LifecycleError) as exc:
        lifecycle_call.call(h.host, never_ready(tmp_path, 3))
    # the first as a single failure says it, then each other one the same way
    assert exc.value.msg == (
        f"isaac-sim-0: {gate(0)}; {STOPPED}; also isaac-sim-1: {gate(1)}; {STOPPED}; "
        f"also isaac-sim-2: {gate(2)}; {STOPPED}"
    )
    fields = exc.value.fields
    assert [f["id"] for f in fields["failed_instances"]] == [0, 1, 2]
    assert fields["failed_instance"] == fields["failed_instances"][0] and fields["done"] == []
    assert all(f["left"] == "stopped" and f["reverted"] is None for f in fields["failed_instances"])
    assert not any(layout.env_file(i) in h.files for i in range(3))


def test_a_call_that_succeeds_has_no_failed_instances(tmp_path):
    out = lifecycle_call.call(scripted(2, running=False).host, params(tmp_path))
    assert out["failed_instance"] is None and out["failed_instances"] == []


def test_a_day_2_start_names_every_instance_that_did_not_start(tmp_path):
    h = scripted(3, running=False)
    for i in (0, 2):
        h.files[layout.env_file(i)] = (NEVER, 0o644)
    h.files[layout.env_file(1)] = (OLD, 0o644)
    with pytest.raises(lifecycle_call.LifecycleError) as exc:
        lifecycle_call.call(h.host, params(tmp_path, action="start", ids=[0, 1, 2]))
    assert exc.value.msg == f"isaac-sim-0: {gate(0)}; also isaac-sim-2: {gate(2)}"
    fields = exc.value.fields
    assert [f["id"] for f in fields["failed_instances"]] == [0, 2] and fields["failed_instance"]["id"] == 0
    assert all(f["left"] == "failed" for f in fields["failed_instances"])
    assert [d["id"] for d in fields["done"]] == [1]


def test_a_call_of_a_run_that_holds_the_host_records_its_job_in_the_lock_while_it_works(tmp_path):
    """The lock says this job runs (its pid) for as long as it does: a run that takes the host over after
    this run's controller ended waits for it (runlock.decide); after the call the record is gone."""
    from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import runlock

    lock = str(tmp_path / "lock" / "isaac-sim.json")
    me = {"id": "ctl:1:2", "controller": "ctl", "pid": 1, "started": "2"}
    runlock.acquire(me, 1000.0, 3600, path=lock, guard=str(tmp_path / "lock" / ".isaac-sim.guard"), record_path="")
    h = scripted(2, running=False)
    seen = []
    run = h.host.run

    def watching(argv):
        seen.append((runlock.read(lock) or {}).get("job"))
        return run(argv)

    h.host.run = watching
    h.host.wall = lambda: 1001.0
    lifecycle_call.call(h.host, params(tmp_path, controller_run=me["id"]), lock=lock, record=str(tmp_path / "r"))
    assert seen and all(job and job["pid"] == os.getpid() for job in seen)
    assert "job" not in runlock.read(lock)
