"""The runtime table (plugins/module_utils/train/runtimes.py): every entry complete, and what slurm.py makes of
each entry written out here in full, as each runtime's own documentation gives its command line (apptainer exec
and build, podman and docker run, enroot create, start and import); test_slurm.py runs node scripts against
stand-in runtimes."""

from __future__ import annotations

import string

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.train import runtimes, slurm

NAMES = ["apptainer", "podman", "docker", "enroot"]
KEYS = {
    "image_suffix",
    "build_tool",
    "build",
    "image",
    "container",
    "run",
    "rc",
    "gpus",
    "bind",
    "env",
    "env_export",
    "gpu_setup",
    "load",
    "create",
    "remove",
    "stop",
    "remove_on_exit",
    "node",
}
# what runtimes.py's templates may name
FIELDS = {"job_id", "node_id", "workdir", "container", "job_gpus", "gpu_devices", "src", "dst", "name", "rc"}
FIELDS |= {"image", "archive"}
BIND = [("/local/cache/kit", "/isaac-sim/kit/cache")]
ENGINE = ["run", "--rm", "--network=host", "--ipc=host", "--entrypoint=", "--workdir=/workspace/isaaclab"]
ENGINE += ["--name=train-$SLURM_JOB_ID-$SLURM_NODEID"]
# the job's container on a node, the words as the node script shows them: (with GPUs, without)
RUN = {
    "apptainer": (
        ["apptainer", "exec", "--containall", "--writable-tmpfs", "--pwd=/workspace/isaaclab", "--nv"]
        + ["--bind=/local/cache/kit:/isaac-sim/kit/cache:rw", "IMAGE", "python", "a b"],
        ["apptainer", "exec", "--containall", "--writable-tmpfs", "--pwd=/workspace/isaaclab"]
        + ["--bind=/local/cache/kit:/isaac-sim/kit/cache:rw", "IMAGE", "python", "a b"],
    ),
    "podman": (
        [
            "podman",
            *ENGINE,
            "--cgroups=disabled",
            "$GPU_DEVICES[@]",
            "--volume=/local/cache/kit:/isaac-sim/kit/cache:rw",
        ]
        + ["--env=WANDB_API_KEY", "IMAGE", "python", "a b"],
        ["podman", *ENGINE, "--cgroups=disabled", "--volume=/local/cache/kit:/isaac-sim/kit/cache:rw"]
        + ["--env=WANDB_API_KEY", "IMAGE", "python", "a b"],
    ),
    "docker": (
        ["docker", *ENGINE, '--gpus="device=$JOB_GPUS"', "--volume=/local/cache/kit:/isaac-sim/kit/cache:rw"]
        + ["--env=WANDB_API_KEY", "IMAGE", "python", "a b"],
        ["docker", *ENGINE, "--volume=/local/cache/kit:/isaac-sim/kit/cache:rw"]
        + ["--env=WANDB_API_KEY", "IMAGE", "python", "a b"],
    ),
    # enroot's hook gives the node's GPUs either way; the command script replaces the entrypoint
    "enroot": (
        ["enroot", "start", "--rw", "--rc=/tmp/.enroot-rc", "--mount=/local/cache/kit:/isaac-sim/kit/cache"]
        + ["--env=WANDB_API_KEY", "IMAGE", "python", "a b"],
        ["enroot", "start", "--rw", "--rc=/tmp/.enroot-rc", "--mount=/local/cache/kit:/isaac-sim/kit/cache"]
        + ["--env=WANDB_API_KEY", "IMAGE", "python", "a b"],
    ),
}
# the job image from the team's image isaac-lab:2.1 on the build host, and its file's name for
# registry.lab:5000/isaac-lab:latest of id sha256:0a45aaed62e1...
BUILD = {
    "apptainer": ["apptainer", "build", "--force", "--fakeroot", "/b/out.partial", "docker-daemon://isaac-lab:2.1"],
    "podman": ["docker", "save", "--output", "/b/out.partial", "isaac-lab:2.1"],
    "docker": ["docker", "save", "--output", "/b/out.partial", "isaac-lab:2.1"],
    "enroot": ["enroot", "import", "--output", "/b/out.partial", "dockerd://isaac-lab:2.1"],
}
IMAGE_FILE = {
    "apptainer": "registry.lab_5000_isaac-lab_latest-0a45aaed62e1.sif",
    "podman": "registry.lab_5000_isaac-lab_latest-0a45aaed62e1.tar",
    "docker": "registry.lab_5000_isaac-lab_latest-0a45aaed62e1.tar",
    "enroot": "registry.lab_5000_isaac-lab_latest-0a45aaed62e1.sqsh",
}
# lines of a node's script besides the run: the image loaded where it is run by id, the container made and
# removed where the runtime makes one, stopped on a cancel, removed when the script ends
NODE_LINES = {
    "apptainer": [],
    "podman": [
        "podman image inspect 0a45aaed62e1 >/dev/null 2>&1 || podman load -q -i /shared/images/lab.tar >/dev/null",
        '  podman stop -t 10 train-"${SLURM_JOB_ID}"-"${SLURM_NODEID}" >/dev/null 2>&1 || true',
        '  podman rm -f train-"${SLURM_JOB_ID}"-"${SLURM_NODEID}" >/dev/null 2>&1 || true',
    ],
    "docker": [
        "docker image inspect 0a45aaed62e1 >/dev/null 2>&1 || docker load -q -i /shared/images/lab.tar >/dev/null",
        '  docker stop -t 10 train-"${SLURM_JOB_ID}"-"${SLURM_NODEID}" >/dev/null 2>&1 || true',
        '  docker rm -f train-"${SLURM_JOB_ID}"-"${SLURM_NODEID}" >/dev/null 2>&1 || true',
    ],
    "enroot": [
        "printf '%s\\n' 'cd /workspace/isaaclab && exec \"$@\"' > \"$LOCAL_CACHE/.enroot-rc\"",
        'enroot create --force --name isaaclab-"${SLURM_JOB_ID}"-"${SLURM_NODEID}" /shared/images/lab.sqsh >/dev/null',
        'enroot remove --force isaaclab-"${SLURM_JOB_ID}"-"${SLURM_NODEID}" >/dev/null 2>&1 || true',
    ],
}
SUFFIX = {"apptainer": ".sif", "podman": ".tar", "docker": ".tar", "enroot": ".sqsh"}


@pytest.mark.parametrize("name", NAMES)
def test_each_runtime_runs_builds_and_names_its_image_as_its_tools_take_it(name):
    rc = "/tmp/.enroot-rc" if name == "enroot" else None
    for gpus, expected in zip((True, False), RUN[name]):
        argv = slurm.runtime_argv(name, "IMAGE", BIND, ["WANDB_API_KEY"], ["python", "a b"], gpus, rc=rc)
        assert [slurm.shown(w) for w in argv] == expected, gpus
    assert slurm.build_argv(name, "isaac-lab:2.1", "/b/out.partial") == BUILD[name]
    assert (
        slurm.image_file("registry.lab:5000/isaac-lab:latest", name, "sha256:0a45aaed62e1252814f0") == IMAGE_FILE[name]
    )


@pytest.mark.parametrize("name", NAMES)
def test_each_runtime_s_node_script_loads_makes_stops_and_removes_as_its_entry_says(name):
    job = slurm.complete(
        {
            "name": "train-ant",
            "runtime": name,
            "release": "6.x",
            "image_file": "/shared/images/lab" + SUFFIX[name],
            "image_id": "sha256:0a45aaed62e1",
            "code_dir": "/shared/jobs/x/code",
            "cache_dir": "/shared/cache",
            "script": "scripts/train.py",
            "args": ["--task=Isaac-Ant-v0"],
            "gpus_per_node": 1,
            "nodes": 1,
            "env_names": ["WANDB_API_KEY"],
            "python": "/isaac-sim/python.sh",
        }
    )
    lines = slurm.node_script(job).splitlines()
    for line in NODE_LINES[name]:
        assert line in lines, (name, line)
    others = {tool for tool in ("podman", "docker", "enroot", "apptainer") if tool != name}
    # only its own tool runs on the node (podman and docker's images are built with docker, not run by it)
    assert not [line for line in lines if line.split(" ", 1)[0] in others]
    run = [line for line in lines if line.startswith(RUN[name][0][0] + " ") and " /isaac-sim/python.sh " in line]
    assert len(run) == 1 and run[0].endswith(" /isaac-sim/python.sh scripts/train.py --task=Isaac-Ant-v0 &")


def test_the_runtimes_are_the_table_s_in_its_order():
    assert slurm.RUNTIMES == tuple(runtimes.RUNTIMES) == tuple(NAMES)


@pytest.mark.parametrize("name", list(runtimes.RUNTIMES))
def test_every_entry_says_everything_a_runtime_differs_in(name):
    entry = runtimes.RUNTIMES[name]
    assert set(entry) == KEYS
    assert entry["image"] in ("file", "id")
    assert entry["image_suffix"].startswith(".")
    # the build runs the program the image module looks for on the build host
    assert entry["build"]("team/lab:1", "/out", None, True)[0] == entry["build_tool"]
    assert entry["run"][0] in (name, entry["build_tool"])
    # an image run by id is loaded on the node; a container made on the node is removed after
    assert (entry["image"] == "id") == bool(entry["load"])
    assert bool(entry["create"]) == bool(entry["remove"]) and (entry["create"] is None or entry["container"])
    assert (entry["env"] is None) != (entry["env_export"] is None)
    assert set(entry["node"]) == {"packages", "command"}
    # every template names only what slurm.py fills in
    words = list(entry["run"]) + list(entry["gpus"]) + [entry["bind"], entry["env"] or "", entry["env_export"] or ""]
    words += [w for key in ("create", "remove", "stop", "remove_on_exit") for w in entry[key] or []]
    words += [w for argv in entry["load"] or () for w in argv] + [entry["container"] or ""]
    words += [entry["rc"]["option"], entry["rc"]["script"]] if entry["rc"] else []
    named = {field for word in words for _text, field, _spec, _conv in string.Formatter().parse(word) if field}
    assert named <= FIELDS, named - FIELDS


def test_another_runtime_is_refused_naming_the_table_s():
    for call in (
        lambda: runtimes.runtime("singularity-ce"),
        lambda: slurm.build_argv("singularity-ce", "x", "/o"),
        lambda: slurm.image_file("x", "singularity-ce", "sha256:0a45"),
    ):
        with pytest.raises(ValueError, match="one of apptainer, podman, docker, enroot"):
            call()


def test_the_image_nodes_read_is_the_archive_for_images_run_by_id_and_the_file_for_the_others():
    podman = slurm.complete({"runtime": "podman", "image_file": "/s/i.tar", "image_id": "sha256:0a45"})
    assert slurm.image_path(podman) == "/s/i.tar" and podman["image"] == "0a45"
    enroot = slurm.complete({"runtime": "enroot", "image_file": "/s/i.sqsh", "image_id": "sha256:0a45"})
    assert slurm.image_path(enroot) == "/s/i.sqsh"
    assert slurm.image_path({"runtime": "unknown", "image": "/s/x"}) == "/s/x"
