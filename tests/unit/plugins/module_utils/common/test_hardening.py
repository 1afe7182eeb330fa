"""docker run arguments that take a container out of its confinement (module_utils/common/hardening.py)."""

from __future__ import annotations

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.common import hardening


@pytest.mark.parametrize(
    "args, text, needle",
    [
        (["--privileged"], "--privileged", "every capability"),
        (["--privileged=true"], "--privileged=true", "every capability"),
        (["--cap-add=SYS_ADMIN"], "--cap-add=SYS_ADMIN", "capability SYS_ADMIN"),
        (["--cap-add", "NET_ADMIN"], "--cap-add=NET_ADMIN", "capability NET_ADMIN"),
        (["--pid=host"], "--pid=host", "host's PID namespace"),
        (["--ipc", "host"], "--ipc=host", "host's IPC namespace"),
        (["--uts=host"], "--uts=host", "UTS"),
        (["--userns=host"], "--userns=host", "user namespace"),
        (["--cgroupns=host"], "--cgroupns=host", "cgroup namespace"),
        (["--security-opt=seccomp=unconfined"], "--security-opt=seccomp=unconfined", "seccomp"),
        (["--security-opt", "apparmor:unconfined"], "--security-opt=apparmor:unconfined", "AppArmor"),
        (["--security-opt=label=disable"], "--security-opt=label=disable", "SELinux"),
        (["--security-opt=label:type:spc_t"], "--security-opt=label:type:spc_t", "super-privileged"),
        (["--security-opt=no-new-privileges:false"], "--security-opt=no-new-privileges:false", "gain privileges"),
        (["--security-opt=systempaths=unconfined"], "--security-opt=systempaths=unconfined", "unmasks"),
        (["--device=/dev/fuse"], "--device=/dev/fuse", "host device"),
        (["--device-cgroup-rule=c 1:* rmw"], "--device-cgroup-rule=c 1:* rmw", "host device"),
        (["--gpus", "all"], "--gpus=all", "host device"),
        (["-v", "/var/run/docker.sock:/var/run/docker.sock"], "--volume=/var/run/docker.sock:/var/run/docker.sock",
         "socket"),
        (["-v/run/docker.sock:/d.sock:ro"], "--volume=/run/docker.sock:/d.sock:ro", "socket"),
        (["--volume=/var/run:/host-run"], "--volume=/var/run:/host-run", "socket"),
        (["--volume=/:/host"], "--volume=/:/host", "socket"),
        (["--mount", "type=bind,source=/run/containerd,target=/c"],
         "--mount=type=bind,source=/run/containerd,target=/c", "socket"),
        (["--mount=type=bind,src=/var/run/docker.sock,dst=/s"], "--mount=type=bind,src=/var/run/docker.sock,dst=/s",
         "socket"),
    ],
)  # fmt: skip
def test_each_way_out_of_the_container_is_refused_as_written_and_named(args, text, needle):
    [(found, why)] = hardening.refused(args)
    assert found == text and needle in why


@pytest.mark.parametrize(
    "args",
    [
        ["--cpus=8", "--label", "team=robots", "--privileged=false", "--pid=container:other"],
        ["--security-opt=no-new-privileges", "--security-opt", "no-new-privileges:true"],
        ["-v", "/data/maps:/maps:ro", "--volume=cache:/cache", "--mount=type=volume,source=cache,target=/c"],
        ["--volume=/var/lib/docker-maps:/m", "--volume=/run/user/1000:/r"],
        ["--cap-drop=ALL", "--network=host", "--ulimit", "nofile=4096"],
    ],
)
def test_arguments_that_keep_the_confinement_pass(args):
    assert hardening.refused(args) == []


def test_an_allowed_argument_passes_whichever_way_either_is_written():
    args = ["--cap-add", "SYS_PTRACE", "--privileged", "-v", "/var/run/docker.sock:/s"]
    assert [text for text, _why in hardening.refused(args, ["--cap-add=SYS_PTRACE"])] == [
        "--privileged",
        "--volume=/var/run/docker.sock:/s",
    ]
    # the allowance names the exact argument: another capability stays refused
    assert [text for text, _why in hardening.refused(["--cap-add=SYS_ADMIN"], ["--cap-add", "SYS_PTRACE"])] == [
        "--cap-add=SYS_ADMIN"
    ]
    assert hardening.refused(args, ["--cap-add=SYS_PTRACE", "--privileged", "--volume=/var/run/docker.sock:/s"]) == []


def test_the_error_names_the_variable_the_argument_whose_it_is_and_the_fix():
    [error] = hardening.errors("isaac_sim_extra_docker_args", "on isaac-sim-0", ["--pid", "host"])
    assert error.startswith("isaac_sim_extra_docker_args: --pid=host shares the host's PID namespace")
    assert "(on isaac-sim-0)" in error and "add '--pid=host' to isaac_sim_allowed_docker_args" in error
