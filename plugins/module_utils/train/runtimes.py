# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The container runtimes a Slurm training job runs in: one entry per runtime, everything that
differs between them. slurm.py writes the node script and the commands from it, the
isaac_sim_train_image module builds the job image with it, and the roles' choice lists, the
slurm_node role's packages and its node probe are checked against it
(tests/unit/test_runtime_choices.py). A new runtime is a new entry here, and its tests.

Each entry:

- image_suffix: the job image's file name ends so, on the build host and the cluster.
- build_tool: the program the build runs on the build host; build: the argv that turns the team's
  Docker image into the job image (source image, output file, `docker save` archive or None,
  fakeroot).
- image: how a node names the image it runs. "file": the job image on the shared path; "id": the
  image's id, loaded on each node from the job image (an archive) when the node lacks it.
- container: the name of the job's container on a node, one per job and node (None: unnamed).
- run: the argv that starts the job's container, up to its options; rc (a command script the
  runtime runs in place of the image's entrypoint: its option, the file's name in the job's local
  cache directory, the script), gpus (the options that give it the job's GPUs), bind (one per
  directory), env (one per variable passed from the node's environment; None: env_export), then
  the image and the training.
- env_export: the variable a name is exported as on the node for the runtime to pass it in
  (None: env).
- gpu_setup: the node script's lines before the run when the job has GPUs.
- load: (argv that finds the image on a node, argv that loads it from the archive), for "id" images.
- create: the argv that makes the node's container from the image before the run (its name:
  container); remove: the argv that removes it after the run; stop: the argv that stops the
  container on a cancel (None: the training's process is sent SIGTERM); remove_on_exit: the argv
  that removes a left-over container when the node script ends.
- node: what a cluster node needs: packages (the slurm_node role's apt packages for it, as the role
  lists them in vars/main.yml, __slurm_node_runtime_packages), command (the program the role's node
  probe looks for, roles/slurm_node/files/slurm-node-probe; None: not looked for).

Words are templates (str.format) of: {job_id} and {node_id} the job's id and the node's number in
the job, {workdir} the code's directory in the container, {container}
the job's container on the node (a name per job and node), {job_gpus} the job's GPUs by their
numbers on the node, {gpu_devices} one --device word per GPU (an array of the node script), {src}
and {dst} a directory on the node and in the container, {name} a variable, {rc} the command
script, {image} what the node runs, {archive} the job image on the shared path.
"""

from __future__ import annotations


def _apptainer_build(source: str, out: str, archive, fakeroot: bool) -> list:
    """A SIF from the local Docker daemon's image (docker-daemon://, as the guide builds it, which
    needs a tag: :latest where none is given), or from a `docker save` archive; --fakeroot lets a
    user without root build (user namespaces and /etc/subuid)."""
    tagged = "@" in source or ":" in source.rsplit("/", 1)[-1]
    daemon = f"docker-daemon://{source}" + ("" if tagged else ":latest")
    origin = f"docker-archive:{archive}" if archive else daemon
    return ["apptainer", "build", "--force"] + (["--fakeroot"] if fakeroot else []) + [out, origin]


def _enroot_import(source: str, out: str, archive, fakeroot: bool) -> list:
    """A squashfs image from the daemon."""
    return ["enroot", "import", "--output", out, f"dockerd://{source}"]


def _docker_save(source: str, out: str, archive, fakeroot: bool) -> list:
    """A `docker save` archive of the team's image that each node loads once (Podman loads
    Docker's archives)."""
    return ["docker", "save", "--output", out, source]


# Podman and Docker: the team's image run by its id, the image's own entrypoint left out (as
# `apptainer exec` leaves it out), in a container named per job and node
def _engine(tool: str, run_options: list, gpus: list, packages: list) -> dict:
    return {
        "image_suffix": ".tar",
        "build_tool": "docker",
        "build": _docker_save,
        "image": "id",
        "container": "train-{job_id}-{node_id}",
        "run": [tool, "run", "--rm", "--network=host", "--ipc=host", "--entrypoint=", "--workdir={workdir}"]
        + ["--name={container}"]
        + run_options,
        "rc": None,
        "gpus": gpus,
        "bind": "--volume={src}:{dst}:rw",
        "env": "--env={name}",
        "env_export": None,
        "gpu_setup": [],
        "load": ([tool, "image", "inspect", "{image}"], [tool, "load", "-q", "-i", "{archive}"]),
        "create": None,
        "remove": None,
        # the training runs in the background; a cancel stops the container (Podman's conmon
        # would die with the step and leave it running)
        "stop": [tool, "stop", "-t", "10", "{container}"],
        # a cancelled job's container goes with it (Docker's would run on under its daemon)
        "remove_on_exit": [tool, "rm", "-f", "{container}"],
        "node": {"packages": packages, "command": None},
    }


RUNTIMES = {
    "apptainer": {
        "image_suffix": ".sif",
        "build_tool": "apptainer",
        "build": _apptainer_build,
        "image": "file",
        "container": None,
        # a clean environment and private /tmp and $HOME, a writable layer that goes with the job
        "run": ["apptainer", "exec", "--containall", "--writable-tmpfs", "--pwd={workdir}"],
        "rc": None,
        # the node's GPUs; the job's device cgroup (Slurm's ConstrainDevices) lets only the job's open
        "gpus": ["--nv"],
        "bind": "--bind={src}:{dst}:rw",
        "env": None,
        # Apptainer's own prefix (--containall passes nothing else); values never appear on a command line
        "env_export": "APPTAINERENV_{name}",
        "gpu_setup": [],
        "load": None,
        "create": None,
        "remove": None,
        "stop": None,
        "remove_on_exit": None,
        # the package the role's slurm_node_apptainer_package names (its default), or a .deb
        "node": {"packages": ["apptainer"], "command": "apptainer"},
    },
    "podman": dict(
        _engine(
            "podman",
            # the container stays in the job's cgroup, so Slurm's CPU, memory and device limits hold
            # and a cancelled job's processes end with it (Docker's daemon starts containers outside it)
            ["--cgroups=disabled"],
            # CDI names (nvidia-ctk cdi generate) of the job's GPUs
            ["{gpu_devices}"],
            # uidmap and slirp4netns: Podman run by the job's own user (rootless)
            ["podman", "uidmap", "slirp4netns"],
        ),
        gpu_setup=[
            "GPU_DEVICES=()",
            'for gpu in ${JOB_GPUS//,/ }; do GPU_DEVICES+=("--device=nvidia.com/gpu=$gpu"); done',
        ],
    ),
    # the NVIDIA container toolkit's --gpus; the Docker engine comes from the docker_engine role
    "docker": _engine("docker", [], ['--gpus="device={job_gpus}"'], []),
    "enroot": {
        "image_suffix": ".sqsh",
        "build_tool": "enroot",
        "build": _enroot_import,
        "image": "file",
        "container": "isaaclab-{job_id}-{node_id}",
        # a container made from the squashfs image on each node (a name per node: its containers may
        # live in a shared $HOME), with a command script in place of the entrypoint: the code
        # directory, then the training
        "run": ["enroot", "start", "--rw"],
        "rc": {"option": "--rc={rc}", "file": ".enroot-rc", "script": 'cd {workdir} && exec "$@"'},
        # enroot's hook brings the node's GPUs; the job's device cgroup lets only the job's open
        "gpus": [],
        "bind": "--mount={src}:{dst}",
        "env": "--env={name}",
        "env_export": None,
        "gpu_setup": [],
        "load": None,
        "create": ["enroot", "create", "--force", "--name", "{container}", "{image}"],
        "remove": ["enroot", "remove", "--force", "{container}"],
        "stop": None,
        "remove_on_exit": None,
        # NVIDIA's .deb packages, installed by the site (no distribution has them); the role checks
        "node": {"packages": [], "command": "enroot"},
    },
}


def runtime(name: str) -> dict:
    """The entry of a runtime; ValueError naming the runtimes for another name."""
    if name not in RUNTIMES:
        raise ValueError(f"runtime {name!r}: one of {', '.join(RUNTIMES)}")
    return RUNTIMES[name]
