"""The runtime table (plugins/module_utils/train/runtimes.py): every entry complete, and what
slurm.py makes of it the same, word for word, as what its runtime branches made before the table
(runtimes-before-the-table.json, written by those branches: every run and build argv, image file
name and completed job in full, every node script as its sha256)."""

from __future__ import annotations

import hashlib
import itertools
import json
import string
from pathlib import Path

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.train import runtimes, slurm

BEFORE = json.loads((Path(__file__).parent / "runtimes-before-the-table.json").read_text())
NAMES = ["apptainer", "podman", "docker", "enroot"]
BINDS = [("/local/cache/kit", "/isaac-sim/kit/cache"), ("/shared/code", "/workspace/isaaclab")]
ENV = ["CUDA_VISIBLE_DEVICES", "WANDB_API_KEY"]
SOURCES = ["isaac-lab-base:latest", "isaac-lab-base", "registry.lab:5000/team/isaac-lab", "lab@sha256:0a45aa"]
SUFFIX = {"apptainer": ".sif", "podman": ".tar", "docker": ".tar", "enroot": ".sqsh"}
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


def cases() -> dict:
    """Each case's output, as the JSON file keeps it."""
    out = {}
    for rt, gpus, rc in itertools.product(NAMES, (True, False), (None, "/tmp/.enroot-rc")):
        argv = slurm.runtime_argv(rt, "IMAGE", BINDS, ENV, ["python", "a b"], gpus, rc=rc)
        out[f"run {rt} gpus={gpus} rc={rc}"] = argv
    for rt, src, archive, fakeroot in itertools.product(NAMES, SOURCES, (None, "/tmp/lab.tar"), (True, False)):
        argv = slurm.build_argv(rt, src, "/b/out.partial", archive=archive, fakeroot=fakeroot)
        out[f"build {rt} {src} archive={archive} fakeroot={fakeroot}"] = argv
    for rt in NAMES:
        name = slurm.image_file("registry.lab:5000/isaac-lab:latest", rt, "sha256:0a45aaed62e1252814f0")
        out[f"image_file {rt}"] = name
        for release, mounts in (("4.x", None), (None, {"kit": "/k"})):
            given = {"runtime": rt, "image_file": "/s/images/i" + SUFFIX[rt], "image_id": "sha256:0a45aaed62e1"}
            given.update(release=release, mounts=mounts)
            out[f"complete {rt} release={release} mounts={mounts}"] = slurm.complete(given)
    for rt, gpus, nodes, archive, local, logs in itertools.product(
        NAMES, (0, 1, 2), (1, 2), (True, False), (True, False), (True, False)
    ):
        job = {
            "name": "train-ant",
            "runtime": rt,
            "release": "6.x",
            "image_file": "/shared/images/lab" + SUFFIX[rt],
            "image_id": "sha256:0a45aaed62e1",
            "code_dir": "/shared/jobs/x/code",
            "cache_dir": "/shared/cache",
            "script": "scripts/train.py",
            "args": ["--task=Isaac-Ant-v0", "$HOME; rm -rf /"],
            "gpus_per_node": gpus,
            "nodes": nodes,
            "env_names": ["WANDB_API_KEY"],
            "python": "/isaac-sim/python.sh",
        }
        if local:
            job["local_cache"] = "/scratch/isaac $x"
        if logs:
            job["logs_dir"] = "/shared/code/logs"
        job = slurm.complete(job)
        if not archive:
            job.pop("image_archive", None)
        text = slurm.node_script(job)
        out[f"node {rt} gpus={gpus} nodes={nodes} archive={archive} local={local} logs={logs}"] = hashlib.sha256(
            text.encode()
        ).hexdigest()
    return json.loads(json.dumps(out))


def test_the_table_makes_what_the_runtime_branches_made_before_it():
    now = cases()
    assert sorted(now) == sorted(BEFORE)
    differ = {name: (BEFORE[name], now[name]) for name in BEFORE if now[name] != BEFORE[name]}
    assert differ == {}


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
