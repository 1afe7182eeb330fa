"""The container policy (module_utils/hostlib/container_policy.py), judged on Docker's own reading
of the arguments: every spelling the hostile-operator run got past the old deny-list, the
Pod-Security-style categories, allowances matched on effect, and docker inspect's shape."""

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import container_policy, docker_cli
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import plan, releases

DATA = "/var/lib/isaac-sim"
RULES = {"bind_roots": [DATA], "gpus": [], "root_ok": False}
BOUND = {"rootvol": {"type": "none", "o": "bind", "device": "/"}}


def refused(args, allowed=(), **rules):
    return container_policy.refused(args, allowed, dict(RULES, volumes=BOUND, **rules))


@pytest.mark.parametrize(
    "args, text, needle",
    [
        # the spellings that passed the old reading of the words (issue: hostile-operator run)
        (["-Pv", "/var/run/docker.sock:/var/run/docker.sock"], "--volume=/var/run/docker.sock:/var/run/docker.sock",
         "Docker's socket"),
        (["--mount", 'type=bind,"source=/run/containerd/containerd.sock",target=/c'],
         "--mount=type=bind,source=/run/containerd/containerd.sock,target=/c", "containerd's socket"),
        (["--security-opt", "no-new-privileges=0"], "--security-opt=no-new-privileges=false", "gain privileges"),
        (["--security-opt=no-new-privileges:f"], "--security-opt=no-new-privileges=false", "gain privileges"),
        (["--security-opt", "no-new-privileges=False"], "--security-opt=no-new-privileges=false", "gain privileges"),
        (["--user=0"], "--user=0", "as root"),
        (["-u", "root:root"], "--user=root:root", "as root"),
        (["-v", "/etc:/host-etc"], "--volume=/etc:/host-etc", "host's configuration"),
        (["-v", "/var/lib/docker:/d"], "--volume=/var/lib/docker:/d", "Docker's own state"),
        (["-v", "/run/systemd:/s"], "--volume=/run/systemd:/s", "systemd's private socket"),
        (["--volumes-from", "other"], "--volumes-from=other", "every volume of another container"),
        (["-v", "rootvol:/host"], "--volume=rootvol:/host", "a local volume's options"),
        (["--mount", "source=v,target=/h,volume-opt=type=none,volume-opt=o=bind,volume-opt=device=/"],
         "--mount=type=volume,source=v,target=/h", "a local volume's options"),
        (["--mount", "source=v,target=/h,volume-opt=type=ext4,volume-opt=device=/dev/sda1"],
         "--mount=type=volume,source=v,target=/h", "the host's /dev/sda1"),
        # and the other spellings Docker accepts
        (["-itv/:/h"], "--volume=/:/h", "Docker's socket"),
        (["-v=/var/run:/r"], "--volume=/var/run:/r", "Docker's socket"),
        (["-v", "./etc:/x"], "--volume=./etc:/x", "host's configuration"),
        (["--mount=type=bind,src=/srv/../etc,dst=/x"], "--mount=type=bind,source=/srv/../etc,target=/x",
         "host path /etc"),
        (["--use-api-socket"], "--mount=type=bind,source=/var/run/docker.sock,target=/var/run/docker.sock",
         "Docker's socket"),
        # Pod Security Standards' categories
        (["--privileged=True"], "--privileged", "every capability"),
        (["--cap-add", "sys_admin"], "--cap-add=SYS_ADMIN", "capability SYS_ADMIN"),
        (["--cap-add=CAP_NET_ADMIN"], "--cap-add=NET_ADMIN", "capability NET_ADMIN"),
        (["--pid=host"], "--pid=host", "host's PID namespace"),
        (["--ipc", "host"], "--ipc=host", "IPC"),
        (["--uts=host"], "--uts=host", "UTS"),
        (["--userns=host"], "--userns=host", "user namespace"),
        (["--cgroupns=host"], "--cgroupns=host", "cgroup namespace"),
        (["--security-opt=seccomp=unconfined"], "--security-opt=seccomp=unconfined", "seccomp"),
        (["--security-opt=seccomp=/etc/my.json"], "--security-opt=seccomp=PROFILE", "profile of its own"),
        (["--security-opt", "apparmor:unconfined"], "--security-opt=apparmor=unconfined", "AppArmor"),
        (["--security-opt=label=disable"], "--security-opt=label=disable", "SELinux"),
        (["--security-opt=label:type:spc_t"], "--security-opt=label=type:spc_t", "other than a container type"),
        (["--security-opt=label=type:container_runtime_t"], "--security-opt=label=type:container_runtime_t",
         "other than a container type"),
        (["--security-opt=label=user:system_u"], "--security-opt=label=user:system_u", "other than a container type"),
        # the review's: a relative device is read from dockerd's working directory, /
        (["--mount", "source=hx,target=/h,volume-opt=type=none,volume-opt=o=bind,volume-opt=device=etc"],
         "--mount=type=volume,source=hx,target=/h", "host path /etc into it"),
        (["--mount", "source=d,target=/d,volume-opt=type=ext4,volume-opt=device=dev/nvme0n1p1"],
         "--mount=type=volume,source=d,target=/d", "the host's /dev/nvme0n1p1"),
        # uid 0 however Go's Atoi reads it
        (["--user=00"], "--user=00", "as root"),
        (["--user=+0:0"], "--user=+0:0", "as root"),
        (["--pid=container:other"], "--pid=container:other", "another container"),
        (["--env-file=/etc/isaac-sim/instance-1.env"], "--env-file=/etc/isaac-sim/instance-1.env", "secrets"),
        (["--security-opt=systempaths=unconfined"], "--security-opt=systempaths=unconfined", "unmasks"),
        (["--device=/dev/fuse"], "--device=/dev/fuse", "host device"),
        (["--device-cgroup-rule=c 1:* rmw"], "--device-cgroup-rule=c 1:* rmw", "host devices"),
        (["--gpus", "all"], "--gpus=all", "GPUs beyond"),
        (["--gpus", '"device=0,1"'], "--gpus=device=0,1", "GPUs beyond"),
        (["-v", "/srv/data:/data"], "--volume=/srv/data:/data", "outside the paths this host allows"),
    ],
)  # fmt: skip
def test_each_way_out_is_refused_however_docker_is_told(args, text, needle):
    [(found, why)] = refused(args)
    assert found == text and needle in why, (found, why)


@pytest.mark.parametrize(
    "args",
    [
        ["--cpus=8", "--label", "team=robots", "--privileged=false", "--network=host", "--network=container:x"],
        ["--security-opt=label=type:container_t", "--security-opt=label=level:s0:c1,c2"],
        ["--security-opt=no-new-privileges", "--security-opt", "no-new-privileges:true"],
        # the last no-new-privileges wins, as the daemon reads them in order
        ["--security-opt=no-new-privileges=false", "--security-opt=no-new-privileges"],
        ["-v", f"{DATA}/maps:/maps:ro", "--volume=cache:/cache", "--mount=type=volume,source=cache,target=/c"],
        [
            "--mount",
            "type=volume,source=n,target=/n,volume-opt=type=nfs,volume-opt=o=addr=10.0.0.1,volume-opt=device=:/x",
        ],
        [
            "--cap-drop=ALL",
            "--ulimit",
            "nofile=4096",
            "--security-opt=seccomp=builtin",
            "--security-opt=label=level:s0",
        ],
        ["--user=1234:1234", "--tmpfs", "/scratch", "-v", "/anonymous"],
    ],
)
def test_arguments_that_keep_the_confinement_pass(args):
    assert refused(args) == []


def test_a_bind_under_a_declared_root_passes_and_a_root_that_holds_the_host_is_refused():
    assert refused(["-v", "/srv/data/set:/data"], bind_roots=[DATA, "/srv/data"]) == []
    # under a declared root, but through .. to the host's own files
    assert (
        refused(["-v", "/srv/data/../../etc:/e"], bind_roots=[DATA, "/srv/data"])[0][0]
        == "--volume=/srv/data/../../etc:/e"
    )
    errors = container_policy.roots_errors(["/srv/data", "/", "/var", "/run/", "/etc/ssl", "data"])
    assert [e.split(":")[1].split()[0] for e in errors] == ["'/'", "'/var'", "'/run/'", "'/etc/ssl'", "'data'"]
    assert "isaac_sim_allowed_bind_roots: 'data' is not an absolute path" in errors[-1]


def test_an_overlay_volume_s_layers_are_judged_as_binds():
    args = ["--mount", 'source=o,target=/o,volume-opt=type=overlay,volume-opt=device=overlay,'
            '"volume-opt=o=lowerdir=/root:/etc,upperdir=/srv/u,workdir=/srv/w"']  # fmt: skip
    found = [why for _t, why in refused(args, bind_roots=[DATA, "/srv"])]
    assert any("/root into it" in w for w in found) and any("/etc into it" in w for w in found)
    assert len(found) == 2  # the layers under a declared root pass


def test_a_mount_s_csv_keeps_a_lone_carriage_return_as_data_as_go_does():
    [(text, why)] = refused(["--mount", "type=bind,target=/x,source=/data/a\rb,source=/etc"])
    assert "host path /etc" in why


def test_root_is_refused_only_where_the_release_runs_as_a_user():
    assert refused(["--user=0"], root_ok=True) == []
    assert refused(["--user=0:0"])[0][0] == "--user=0:0"


def test_the_gpu_the_plan_gives_passes_and_no_other():
    assert refused(["--gpus=device=1"], gpus=["1"]) == []
    assert [t for t, _w in refused(["--gpus=device=2", "--gpus=all"], gpus=["1"])] == ["--gpus=device=2", "--gpus=all"]


def test_an_allowance_matches_what_docker_makes_of_it_however_either_is_written():
    args = ["--cap-add", "sys_ptrace", "--privileged", "-Pv", "/var/run/docker.sock:/s"]
    assert [t for t, _w in refused(args, ["--cap-add=CAP_SYS_PTRACE"])] == [
        "--privileged",
        "--volume=/var/run/docker.sock:/s",
    ]
    # the bind is allowed by its source, whatever its target and spelling
    assert [t for t, _w in refused(args, ["--cap-add=SYS_PTRACE", "--volume=/run/docker.sock:/x"])] == ["--privileged"]
    # one capability allowed is not another, one socket not another
    assert [t for t, _w in refused(["--cap-add=SYS_ADMIN"], ["--cap-add", "SYS_PTRACE"])] == ["--cap-add=SYS_ADMIN"]
    assert refused(["-v", "/run/containerd/containerd.sock:/c"], ["--volume=/var/run/docker.sock:/s"]) != []


def test_the_error_names_the_variable_the_argument_whose_it_is_and_the_fix():
    [error] = container_policy.errors("isaac_sim_extra_docker_args", "on isaac-sim-0", ["--pid", "host"], (), RULES)
    assert error.startswith("isaac_sim_extra_docker_args: --pid=host shares the host's PID namespace")
    assert "(on isaac-sim-0)" in error and "add '--pid=host' to isaac_sim_allowed_docker_args" in error
    [error] = container_policy.errors(
        "isaac_sim_extra_docker_args", "on isaac-sim-0", ["--privileged", "no"], (), RULES
    )
    assert "'no' is not an option: Docker stops reading options there and takes it as the image" in error
    assert error.endswith("Fix: write the arguments as docker run takes them, one word per item.")


def test_docker_inspect_is_judged_as_the_arguments_are():
    """A created container as Docker reports it (API 1.41, Docker 20.10): the same findings."""
    inspected = {
        "Name": "/isaac-sim-0",
        "Config": {"User": "0"},
        "HostConfig": {
            "Binds": ["/var/run/docker.sock:/var/run/docker.sock", f"{DATA}/0/cache/kit:/isaac-sim/kit/cache:rw"],
            "Mounts": [{"Type": "volume", "Source": "rootvol", "Target": "/h"}],
            "CapAdd": ["CAP_SYS_ADMIN"],
            "SecurityOpt": ["no-new-privileges", "no-new-privileges=0", "disable"],
            "MaskedPaths": [],
            "DeviceRequests": [{"Driver": "", "Count": 0, "DeviceIDs": ["0"], "Capabilities": [["gpu"]]}],
            "PidMode": "host",
            # Docker's default on cgroup v1: shown for every container, asked for or not
            "CgroupnsMode": "host",
        },
    }
    judged = container_policy.judge(inspected, dict(RULES, gpus=["0"], volumes=BOUND, inspected=True))
    assert sorted(key for key, _t, _w in judged) == sorted(
        [
            ("bind", "/run/docker.sock"),
            ("bind", "/"),
            ("cap-add", "SYS_ADMIN"),
            ("no-new-privileges", "false"),
            ("label", "disable"),
            ("systempaths", "unconfined"),
            ("pid", "host"),
            ("user", "root"),
        ]
    )


@pytest.mark.parametrize("release", list(releases.RELEASES))
def test_every_release_s_own_arguments_pass_the_policy(release):
    """What the plan itself gives an instance (its caches, its GPU, its user, its confinement) passes
    the check the unit and the audit make of the created container."""
    profile = releases.RELEASES[release]
    cfg = {
        "release": release, "data_root": DATA, "memory_limit": "32g", "shm_size": "2g", "health_interval": 30,
        "health_retries": 3, "ready_timeout": 300, "hub_dir": f"{DATA}/hub-cache",
    }  # fmt: skip
    for mode in profile["profiles"]:
        ports = {kind: 40000 + n for n, kind in enumerate(profile["ports"])}
        inst = plan._instance(cfg, profile, mode, 0, ports, 1)
        rules = {"bind_roots": [DATA], "gpus": ["1"], "root_ok": profile["uid"] == 0}
        assert container_policy.judge(docker_cli.config(inst["docker_args"]), rules) == [], (release, mode)
