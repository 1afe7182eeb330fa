# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Training jobs on a Slurm cluster, as text and argument lists: the batch script sbatch takes,
the script each node runs, the container runtime's command, and what sinfo, squeue and sacct
say. Pure: the module and the role run these; the unit tests read what they generate.

A job is one batch script that starts one task per node (srun); each task copies the shared
Isaac Sim caches to the node's local disk, runs the training in the job's container runtime
(one process, or torchrun with one process per GPU), and the first node copies the caches back
whatever the training's exit. The job's exit status is the training's.
"""

from __future__ import annotations

import hashlib
import json
import re
import shlex

from ansible_collections.isaacsim.fleet.plugins.module_utils import releases

RUNTIMES = ("apptainer", "podman", "docker", "enroot")
# where the image the jobs run lives on the cluster, per runtime
IMAGE_SUFFIX = {"apptainer": ".sif", "podman": ".tar", "docker": ".tar", "enroot": ".sqsh"}
WORKDIR = "/workspace/isaaclab"
RENDEZVOUS_PORT = 29500
# job states (squeue(1)) after which a job does not run again
FINISHED = {
    "BOOT_FAIL",
    "CANCELLED",
    "COMPLETED",
    "DEADLINE",
    "FAILED",
    "NODE_FAIL",
    "OUT_OF_MEMORY",
    "PREEMPTED",
    "REVOKED",
    "SPECIAL_EXIT",
    "TIMEOUT",
}
SQUEUE_FORMAT = "%i|%T|%M|%N|%r"
SACCT_FIELDS = "JobID,State,ExitCode,Elapsed,NodeList"
SINFO_FORMAT = "%P|%D|%c|%m|%G|%l"

# a node's variable inside a generated word; every other character of a word is taken as written
_VAR_OPEN, _VAR_CLOSE = "\ue000", "\ue001"
# NAME, or NAME[@] for each element of an array as its own word
_VAR = re.compile(f"{_VAR_OPEN}([A-Z_][A-Z0-9_]*(?:\\[@\\])?){_VAR_CLOSE}")
_TIME = re.compile(r"^(?:(\d+)-)?(\d+)(?::(\d+))?(?::(\d+))?$")
_GRES_GPU = re.compile(r"(?:^|,)gpu(?::[^:,()]+)?:(\d+)")
_SIZE = re.compile(r"^(\d+)([KMGT]?)$", re.IGNORECASE)
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


def node(name: str) -> str:
    """A variable of the node ($SLURM_JOB_ID, ...) in a word of a generated script: it expands
    there; the words a user gives (arguments, paths) never do."""
    return f"{_VAR_OPEN}{name}{_VAR_CLOSE}"


def shown(word: str) -> str:
    """A generated word as a person reads it ($NAME for the node's variables)."""
    return _VAR.sub(r"$\1", word)


def parse_time(text):
    """Seconds of a Slurm time limit (minutes, minutes:seconds, hours:minutes:seconds, days-hours,
    days-hours:minutes, days-hours:minutes:seconds); 0 for infinite/unlimited; None when it does not parse."""
    text = str(text).strip().lower()
    if text in ("infinite", "unlimited"):
        return 0
    match = _TIME.match(text)
    if not match:
        return None
    days, first, second, third = match.groups()
    if days is not None:
        # days-hours[:minutes[:seconds]]
        hours, minutes, seconds = int(first), int(second or 0), int(third or 0)
        total = int(days) * 86400 + hours * 3600 + minutes * 60 + seconds
    elif third is not None:
        total = int(first) * 3600 + int(second) * 60 + int(third)
    elif second is not None:
        total = int(first) * 60 + int(second)
    else:
        total = int(first) * 60
    return total


def memory_mib(text):
    """MiB of a Slurm memory size (a number is MiB; K, M, G, T suffixes), or None."""
    match = _SIZE.match(str(text).strip())
    if not match:
        return None
    value, unit = int(match.group(1)), match.group(2).upper()
    return {"K": value // 1024, "": value, "M": value, "G": value * 1024, "T": value * 1024 * 1024}[unit]


def parse_sinfo(text: str) -> dict:
    """{partition: {"default", "nodes", "cpus", "memory_mib", "gpus", "max_time"}} from
    `sinfo -h -e -o SINFO_FORMAT` (one line per partition and node configuration); gpus and the
    others are the most one node of the partition has, max_time in seconds (0: none)."""
    out = {}
    for line in text.splitlines():
        fields = line.strip().split("|")
        if len(fields) != 6:
            continue
        name, nodes, cpus, memory, gres, limit = fields
        default = name.endswith("*")
        name = name.rstrip("*")
        gpus = max((int(n) for n in _GRES_GPU.findall(gres)), default=0)
        part = out.setdefault(
            name, {"default": default, "nodes": 0, "cpus": 0, "memory_mib": 0, "gpus": 0, "max_time": None}
        )
        part["nodes"] += int(nodes) if nodes.isdigit() else 0
        part["cpus"] = max(part["cpus"], int(cpus.rstrip("+")) if cpus.rstrip("+").isdigit() else 0)
        part["memory_mib"] = max(part["memory_mib"], int(memory.rstrip("+")) if memory.rstrip("+").isdigit() else 0)
        part["gpus"] = max(part["gpus"], gpus)
        part["max_time"] = parse_time(limit)
    return out


def check_request(job: dict, partitions: dict) -> list:
    """Errors in a job's request against what the cluster's partitions have (parse_sinfo), each
    naming the variable and the fix, before anything is submitted."""
    errors = []
    name = job.get("partition") or next((p for p, v in partitions.items() if v["default"]), None)
    if not partitions:
        return ["train_partition: the cluster reports no partition (sinfo). Fix: check that slurmctld answers."]
    if name not in partitions:
        errors.append(
            f"train_partition: {job.get('partition')!r} is not a partition of the cluster. Fix: one of "
            f"{', '.join(sorted(partitions))}."
        )
        return errors
    part = partitions[name]
    seconds = parse_time(job.get("time", ""))
    if seconds is None:
        errors.append(
            f"train_time: {job.get('time')!r} does not parse as a Slurm time. Fix: minutes, HH:MM:SS or "
            "D-HH:MM:SS (e.g. 23:00:00)."
        )
    elif part["max_time"] and (seconds == 0 or seconds > part["max_time"]):
        errors.append(
            f"train_time: {job.get('time')} is longer than partition {name} allows "
            f"({_clock(part['max_time'])}). Fix: ask for less time."
        )
    gpus, nodes = int(job.get("gpus_per_node") or 0), int(job.get("nodes") or 1)
    if gpus > part["gpus"]:
        errors.append(
            f"train_gpus_per_node: {gpus}, and no node of partition {name} has more than {part['gpus']}. "
            "Fix: ask for fewer per node (and more nodes), or use a partition with bigger nodes."
        )
    if nodes > part["nodes"]:
        errors.append(f"train_nodes: {nodes}, and partition {name} has {part['nodes']}. Fix: ask for fewer nodes.")
    cpus = int(job.get("cpus_per_node") or 1)
    if part["cpus"] and cpus > part["cpus"]:
        errors.append(
            f"train_cpus_per_node: {cpus}, and no node of partition {name} has more than {part['cpus']}. "
            "Fix: ask for fewer."
        )
    memory = job.get("memory")
    if memory:
        mib = memory_mib(memory)
        if mib is None:
            errors.append(f"train_memory: {memory!r} is not a size. Fix: e.g. 64G or 32000 (MiB).")
        elif part["memory_mib"] and mib > part["memory_mib"]:
            errors.append(
                f"train_memory: {memory}, and no node of partition {name} has more than {part['memory_mib']} MiB. "
                "Fix: ask for less."
            )
    if not _NAME.match(str(job.get("name") or "")):
        errors.append(
            f"train_job_name: {job.get('name')!r}. Fix: letters, digits, dot, dash and underscore, 64 at most."
        )
    return errors


def _clock(seconds: int) -> str:
    days, rest = divmod(int(seconds), 86400)
    text = f"{rest // 3600:02d}:{rest % 3600 // 60:02d}:{rest % 60:02d}"
    return f"{days}-{text}" if days else text


def parse_squeue(line: str):
    """{"id", "state", "elapsed", "nodes", "reason"} from one `squeue -h -o SQUEUE_FORMAT` line, or None."""
    fields = line.strip().split("|")
    if len(fields) != 5:
        return None
    job_id, state, elapsed, nodes, reason = fields
    return {"id": job_id, "state": state, "elapsed": elapsed, "nodes": nodes, "reason": reason}


def exit_of(text: str):
    """(exit code, signal) of Slurm's "code:signal" ExitCode, or None."""
    match = re.match(r"^(\d+):(\d+)$", (text or "").strip())
    return (int(match.group(1)), int(match.group(2))) if match else None


def parse_sacct(text: str, job_id: str):
    """The job's own line of `sacct -n -P -o SACCT_FIELDS -j ID` (or `sacct -c`, which reads the
    job completion log): {"id", "state", "exit_code", "signal", "elapsed", "nodes"}, or None."""
    for line in text.splitlines():
        fields = line.strip().split("|")
        if len(fields) != 5 or fields[0] != str(job_id):
            continue
        code = exit_of(fields[2]) or (None, None)
        return {
            # "CANCELLED by 0": the state's first word
            "state": fields[1].split()[0] if fields[1] else "",
            "id": fields[0],
            "exit_code": code[0],
            "signal": code[1],
            "elapsed": fields[3],
            "nodes": fields[4],
        }
    return None


def status_of(job_id, squeue_text: str, sacct_text: str):
    """A job's state from what squeue and sacct say of it: {"id", "state", "elapsed", "nodes",
    "reason", "exit_code", "signal", "finished"}, or None when neither knows it. Finished only
    once its completion record is there (the exit status comes with it)."""
    done = parse_sacct(sacct_text or "", job_id)
    if done and done["state"] in FINISHED:
        return dict(done, reason="", finished=True)
    queued = next(
        (q for q in map(parse_squeue, (squeue_text or "").splitlines()) if q and q["id"] == str(job_id)), None
    )
    if queued:
        return dict(queued, exit_code=None, signal=None, finished=False)
    return None


def script_dir(job: dict) -> str:
    """The directory of a job's generated scripts, named by what the job is: a running job's
    scripts are never rewritten by the next submission, an identical one reuses them."""
    text = json.dumps(job, sort_keys=True, default=str)
    return f"{job['name']}-{hashlib.sha256(text.encode()).hexdigest()[:12]}"


def image_file(source: str, runtime: str) -> str:
    """The file name of a job image on the cluster, from the team's image name."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", source) + IMAGE_SUFFIX[runtime]


def complete(job: dict) -> dict:
    """The job as the scripts take it, from what the playbook gives: the image from image_file
    (its path on the cluster) and image_id (podman and docker nodes run it by id, loaded from
    the file), the cache mounts of the release when none are given."""
    job = dict(job)
    if job.get("runtime") in ("podman", "docker"):
        job["image"] = str(job.get("image_id") or "").rsplit(":", maxsplit=1)[-1]
        job["image_archive"] = job.get("image_file")
    else:
        job["image"] = job.get("image_file")
    if not job.get("mounts"):
        job["mounts"] = releases.RELEASES[job.get("release") or "6.x"]["mounts"]
    return job


def cache_binds(cache: str, mounts: dict) -> list:
    """(host path, container path) of each cache directory of the job's node-local copy."""
    return [(f"{cache}/{sub}", target) for sub, target in sorted(mounts.items())]


def runtime_argv(runtime: str, image: str, binds, env_names, command, gpus: bool) -> list:
    """The command that runs `command` in the job's image on a node (words of the node script;
    node() marks the node's variables in them). env_names: variables passed from the node's
    environment. The image's own entrypoint is not run, as `apptainer exec` does not run it.

    GPUs: Apptainer's --nv and enroot's hook bring the node's GPUs, and the job's device cgroup
    (Slurm's ConstrainDevices) lets only the job's open; Podman and Docker are given the job's
    GPUs by their numbers on the node (JOB_GPUS, from Slurm's SLURM_STEP_GPUS)."""
    if runtime not in RUNTIMES:
        raise ValueError(f"runtime {runtime!r}: one of {', '.join(RUNTIMES)}")
    if runtime == "apptainer":
        # a clean environment and private /tmp and $HOME, a writable layer that goes with the job
        argv = ["apptainer", "exec", "--containall", "--writable-tmpfs", f"--pwd={WORKDIR}"]
        argv += ["--nv"] if gpus else []
        argv += [f"--bind={src}:{dst}:rw" for src, dst in binds]
        argv += [f"--env={name}={node(name)}" for name in env_names]
        return argv + [image] + list(command)
    if runtime == "enroot":
        argv = ["enroot", "start", "--rw"]
        argv += [f"--mount={src}:{dst}" for src, dst in binds]
        argv += [f"--env={name}" for name in env_names]
        return argv + [image] + list(command)
    argv = [runtime, "run", "--rm", "--network=host", "--ipc=host", "--entrypoint=", f"--workdir={WORKDIR}"]
    argv += [f"--name={container_name()}"]
    if runtime == "podman":
        # the container stays in the job's cgroup, so Slurm's CPU, memory and device limits hold
        # and a cancelled job's processes end with it (Docker's daemon starts containers outside it)
        argv += ["--cgroups=disabled"]
    if gpus:
        # CDI names for Podman (nvidia-ctk cdi generate), the toolkit's --gpus for Docker
        argv += [node("GPU_DEVICES[@]")] if runtime == "podman" else [f'--gpus="device={node("JOB_GPUS")}"']
    argv += [f"--volume={src}:{dst}:rw" for src, dst in binds]
    argv += [f"--env={name}" for name in env_names]
    return argv + [image] + list(command)


def container_name() -> str:
    """The name of a job's container on a node (Podman and Docker), one per job and node."""
    return f"train-{node('SLURM_JOB_ID')}-{node('SLURM_NODEID')}"


def training_command(job: dict) -> list:
    """The training inside the container: python on the script with its arguments, or torchrun
    with one process per GPU of each node when the job has more than one GPU in all."""
    python = shlex.split(job.get("python") or "/isaac-sim/python.sh")
    gpus, nodes = int(job.get("gpus_per_node") or 0), int(job.get("nodes") or 1)
    args = [str(a) for a in job.get("args") or []]
    if gpus * nodes <= 1:
        return python + [job["script"]] + args
    return (
        python
        + ["-m", "torch.distributed.run", f"--nnodes={node('SLURM_NNODES')}", f"--nproc_per_node={gpus}"]
        + [f"--node_rank={node('SLURM_NODEID')}", f"--rdzv_id={node('SLURM_JOB_ID')}", "--rdzv_backend=c10d"]
        + [f"--rdzv_endpoint={node('MASTER_ADDR')}:{RENDEZVOUS_PORT}", job["script"]]
        + args
    )


def _word(word: str) -> str:
    """A word of a generated shell script: the node's variables (node()) expand, nothing else does."""
    out, at = [], 0
    for match in _VAR.finditer(str(word)):
        if match.start() > at:
            out.append(shlex.quote(str(word)[at : match.start()]))
        out.append(f'"${{{match.group(1)}}}"')
        at = match.end()
    if at < len(str(word)) or not out:
        out.append(shlex.quote(str(word)[at:]))
    return "".join(out)


def line(argv) -> str:
    return " ".join(_word(w) for w in argv)


def batch_script(job: dict, node_script: str, managed: str = "Ansible managed (isaacsim.fleet)") -> str:
    """What sbatch runs: the resources asked for, then one task per node running node_script."""
    directives = [
        f"--job-name={job['name']}",
        f"--nodes={int(job.get('nodes') or 1)}",
        "--ntasks-per-node=1",
        f"--cpus-per-task={int(job.get('cpus_per_node') or 1)}",
        f"--time={job['time']}",
        f"--output={job['log_dir']}/slurm-%j.out",
    ]
    if job.get("partition"):
        directives.append(f"--partition={job['partition']}")
    if job.get("account"):
        directives.append(f"--account={job['account']}")
    if int(job.get("gpus_per_node") or 0):
        directives.append(f"--gpus-per-node={int(job['gpus_per_node'])}")
    if job.get("memory"):
        directives.append(f"--mem={job['memory']}")
    directives += [str(d) for d in job.get("sbatch_options") or []]
    text = ["#!/bin/bash"] + [f"#SBATCH {d}" for d in directives]
    text += [f"# {managed}", "set -eo pipefail"]
    # site modules (a proxy, a newer Apptainer) before anything runs
    text += [f"module load {shlex.quote(str(m))}" for m in job.get("modules") or []]
    text += [
        # the first node's address as slurm.conf gives it (NodeAddr, its name where none is set)
        'MASTER_NODE="$(scontrol show hostnames "$SLURM_JOB_NODELIST" | head -n 1)"',
        'MASTER_ADDR="$(scontrol show node "$MASTER_NODE" | sed -n \'s/.*NodeAddr=\\([^ ]*\\).*/\\1/p\')"',
        'MASTER_ADDR="${MASTER_ADDR:-$MASTER_NODE}"',
        "export MASTER_ADDR",
        # one task per node; the job fails as soon as one node's training does
        f"exec srun --kill-on-bad-exit=1 --ntasks-per-node=1 bash {shlex.quote(node_script)}",
    ]
    return "\n".join(text) + "\n"


def node_script(job: dict, managed: str = "Ansible managed (isaacsim.fleet)") -> str:
    """What each node runs: the caches in, the training, the caches back (first node), its exit.

    job: name, runtime, image (the SIF or squashfs file, or for podman and docker the image's
    id, with image_archive the file each node loads it from), code_dir (the job's code on the
    shared file system), cache_dir (the shared caches), mounts ({cache subdirectory: path in the
    container}), python, script, args, gpus_per_node, nodes, env_names."""
    runtime = job["runtime"]
    shared = job["cache_dir"]
    # the node's own disk: Slurm's per-job $TMPDIR where the site sets one
    local = _word(job["local_cache"]) if job.get("local_cache") else '"${TMPDIR:-/tmp}/isaac-sim-cache-$SLURM_JOB_ID"'
    binds = cache_binds(node("LOCAL_CACHE"), job["mounts"]) + [(job["code_dir"], WORKDIR)]
    env_names = sorted(set(job.get("env_names") or []) | {"CUDA_VISIBLE_DEVICES", "MASTER_ADDR"})
    env_names += ["SLURM_JOB_ID", "SLURM_NNODES", "SLURM_NODEID"]
    # enroot runs a container made from the job's squashfs image on each node, then removes it
    image = f"isaaclab-{node('SLURM_JOB_ID')}" if runtime == "enroot" else job["image"]
    gpus = bool(int(job.get("gpus_per_node") or 0))
    run = runtime_argv(runtime, image, binds, env_names, training_command(job), gpus)
    dirs = " ".join(_word(f"{node('LOCAL_CACHE')}/{sub}") for sub in sorted(job["mounts"]))
    text = [
        "#!/bin/bash",
        f"# {managed}",
        "set -o pipefail",
        f"SHARED_CACHE={_word(shared)}",
        f"LOCAL_CACHE={local}",
        # Isaac Sim reads and writes its caches a lot: the node's disk, not the shared file system
        f'mkdir -p {dirs} && cp -a "$SHARED_CACHE/." "$LOCAL_CACHE/" 2>/dev/null || true',
        "copy_back() {",
    ]
    if runtime in ("podman", "docker"):
        # a cancelled job's container goes with it (Docker's would run on under its daemon)
        text.append(f"  {runtime} rm -f {_word(container_name())} >/dev/null 2>&1 || true")
    text += [
        '  if [ "$SLURM_NODEID" = 0 ]; then cp -a "$LOCAL_CACHE/." "$SHARED_CACHE/" || true; fi',
        '  rm -rf "$LOCAL_CACHE"',
        "}",
        "trap copy_back EXIT",
        # the job's GPUs by their numbers on the node (CUDA_VISIBLE_DEVICES counts from 0 in
        # the job's device cgroup)
        'JOB_GPUS="${SLURM_STEP_GPUS:-${SLURM_JOB_GPUS:-}}"',
    ]
    if runtime == "podman" and gpus:
        text += [
            "GPU_DEVICES=()",
            'for gpu in ${JOB_GPUS//,/ }; do GPU_DEVICES+=("--device=nvidia.com/gpu=$gpu"); done',
        ]
    if runtime in ("podman", "docker") and job.get("image_archive"):
        # the image comes to each node once, from the archive on the shared path; by its id, so
        # a rebuilt image under the same tag is loaded again
        text.append(
            f"{runtime} image inspect {_word(job['image'])} >/dev/null 2>&1 || "
            f"{runtime} load -q -i {_word(job['image_archive'])} >/dev/null"
        )
    if runtime == "enroot":
        text.append(f"enroot create --force --name {_word(image)} {_word(job['image'])} >/dev/null")
    # the training runs in the background so that a cancel (scancel's SIGTERM) is handled at
    # once: the container is stopped (Podman's conmon would die with the step and leave it
    # running), then the caches go back; bash defers a trap while a foreground command runs
    if runtime in ("podman", "docker"):
        stop = f"  {runtime} stop -t 20 {_word(container_name())} >/dev/null 2>&1 || true"
    else:
        stop = '  kill -TERM "$TRAINING" 2>/dev/null || true'
    text += [
        f"{line(run)} &",
        "TRAINING=$!",
        "on_signal() {",
        stop,
        '  wait "$TRAINING"',
        "  exit 143",
        "}",
        "trap on_signal TERM INT",
        'wait "$TRAINING"',
        "status=$?",
    ]
    if runtime == "enroot":
        text.append(f"enroot remove --force {_word(image)} >/dev/null 2>&1 || true")
    text += ['echo "isaacsim.fleet: training on node $SLURM_NODEID exited with $status"', "exit $status"]
    return "\n".join(text) + "\n"


def build_argv(runtime: str, source_image: str, out: str, archive=None, fakeroot=True) -> list:
    """The command that turns the team's Docker image into what the runtime runs, on the build host.

    apptainer: a SIF from the local Docker daemon's image (docker-daemon://, as the guide builds
    it, which needs a tag: :latest where none is given), or from a `docker save` archive;
    --fakeroot lets a user without root build (user namespaces and /etc/subuid). enroot: a
    squashfs image from the daemon. podman and docker: a `docker save` archive of the team's
    image that each node loads once (Podman loads Docker's archives)."""
    if runtime == "apptainer":
        tagged = "@" in source_image or ":" in source_image.rsplit("/", 1)[-1]
        daemon = f"docker-daemon://{source_image}" + ("" if tagged else ":latest")
        source = f"docker-archive:{archive}" if archive else daemon
        return ["apptainer", "build", "--force"] + (["--fakeroot"] if fakeroot else []) + [out, source]
    if runtime == "enroot":
        return ["enroot", "import", "--output", out, f"dockerd://{source_image}"]
    if runtime in ("podman", "docker"):
        return ["docker", "save", "--output", out, source_image]
    raise ValueError(f"runtime {runtime!r}: one of {', '.join(RUNTIMES)}")


def submitted_id(text: str):
    """The job id of `sbatch --parsable` ("123" or "123;cluster"), or None."""
    first = (text or "").strip().splitlines()[:1]
    job = first[0].split(";", 1)[0] if first else ""
    return job if job.isdigit() else None


def needs_build(source_id: str, recorded) -> bool:
    """Whether the cluster's image must be built and copied again: the source image's id (its
    digest) differs from the one recorded beside the image when it was last built."""
    return not recorded or recorded.strip() != (source_id or "").strip()


def progress_line(job: dict) -> str:
    """One line of a job's progress for a person: state, elapsed, nodes (or why it waits)."""
    where = job.get("nodes") or ""
    if job.get("state") == "PENDING" and job.get("reason") not in (None, "", "None"):
        where = f"waiting: {job['reason']}"
    return f"job {job.get('id')} {job.get('state', '?')} {job.get('elapsed', '')} {where}".rstrip()


def parse_slurmd_c(text: str) -> dict:
    """What `slurmd -C` finds of a node ("NodeName=n1 CPUs=2 Boards=1 ... RealMemory=24105"), as
    {key: value}; the first line only (the second is its uptime)."""
    first = (text or "").strip().splitlines()[:1]
    return dict(word.split("=", 1) for word in (first[0].split() if first else []) if "=" in word)


def gres_conf(node: str, devices) -> str:
    """The node's gres.conf lines: one GPU per device file found (/dev/nvidia0, ...), in order.
    Slurm wants character devices here (a plain file makes the node INVAL)."""
    return "".join(f"NodeName={node} Name=gpu File={dev}\n" for dev in sorted(devices, key=_device_order))


def _device_order(path: str):
    match = re.search(r"(\d+)$", path)
    return (int(match.group(1)) if match else -1, path)
