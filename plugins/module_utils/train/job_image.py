# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The job image a Slurm cluster's jobs run, made on the build host from the team's Docker image
only when that image changed: its id (the digest of its configuration) names the file, so a new
image never replaces the file a queued job is about to run. The runtime's build: runtimes.py."""

from __future__ import annotations

import os

from ansible_collections.isaacsim.fleet.plugins.module_utils.train import runtimes, slurm


class ImageError(Exception):
    """Why the job image cannot be had; result: what the module returns with the message."""

    def __init__(self, msg: str, **result):
        super().__init__(msg)
        self.result = result


class BuildHost:
    """The build host as the build sees it: which(name) -> the program's path or None;
    run(argv) -> (rc, stdout, stderr). The module fills it with real calls (bind)."""

    def __init__(self, which, run):
        self.which, self.run = which, run


def bind(module) -> BuildHost:
    """The real build host, for a module running on it."""
    return BuildHost(module.get_bin_path, module.run_command)


def ensure(host: BuildHost, source: str, runtime: str, build_dir: str, present=False, fakeroot=True, check=False):
    """The job image of the team's image `source` for `runtime`, in build_dir: {"changed", "built",
    "id", "file", "path"} and, when a build is due, "command". present: the cluster has the file
    of this id already (nothing is built); check: say whether a build is due, build nothing."""
    docker = host.which("docker")
    if not docker:
        raise ImageError("train_image: the build host has no docker command. Fix: build where the image is.")
    rc, out, err = host.run([docker, "image", "inspect", "--format", "{{.Id}}", source])
    if rc != 0:
        raise ImageError(
            f"train_image: {source!r} is not an image of the build host's Docker ({err.strip()}). "
            "Fix: build or pull it there, or name one that `docker images` lists."
        )
    image_id = out.strip()
    name = slurm.image_file(source, runtime, image_id)
    done = {"id": image_id, "file": name, "path": os.path.join(build_dir, name)}
    if present:
        return dict(done, changed=False, built=False)
    tool = runtimes.runtime(runtime)["build_tool"]
    if not host.which(tool):
        raise ImageError(
            f"train_runtime: {runtime} images are built with {tool}, which the build host "
            "lacks. Fix: install it there (Apptainer: https://apptainer.org/docs/admin/main/installation.html)."
        )
    # built beside the file and moved over it: a build that stops half way never stands as the image
    partial = done["path"] + ".partial"
    argv = slurm.build_argv(runtime, source, partial, fakeroot=fakeroot)
    built = dict(done, changed=True, built=True, command=argv)
    if check:
        return built
    os.makedirs(build_dir, exist_ok=True)
    if os.path.exists(partial):
        os.remove(partial)
    rc, out, err = host.run(argv)
    if rc != 0:
        raise ImageError(f"{' '.join(argv)} failed ({rc}): {(err or out).strip()}", command=argv)
    os.replace(partial, done["path"])
    return built
