# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Training jobs on a Slurm cluster, as text and argument lists: the batch script sbatch takes,
the script each node runs, the container runtime's command, and what sinfo, scontrol and sacct
say. Pure: the module and the role run these; the unit tests read what they generate.

A job is one batch script that starts one task per node (srun); each task copies the shared
Isaac Sim caches to the node's local disk, runs the training in the job's container runtime
(one process, or torchrun with one process per GPU), and the first node copies the caches back
whatever the training's exit. The job's exit status is the training's.
"""

from __future__ import annotations

import re
import shlex
import time

from ansible_collections.isaacsim.fleet.plugins.module_utils.common import parse
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import releases
from ansible_collections.isaacsim.fleet.plugins.module_utils.train import runtimes

# the runtimes' names (runtimes.RUNTIMES has what each one does)
RUNTIMES = tuple(runtimes.RUNTIMES)
WORKDIR = "/workspace/isaaclab"
RENDEZVOUS_PORT = 29500
# job states (squeue(1), JOB STATE CODES) after which a job does not run again
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
# a job slurmctld has ended waits in COMPLETING until each of its nodes says its end is done: a node
# that refuses slurmctld's messages (a munge key not the controller's) keeps it there, and Slurm's
# reason says nothing of the node
COMPLETING = "COMPLETING"
SACCT_FIELDS = "JobID,State,ExitCode,Elapsed,NodeList"
SINFO_FORMAT = "%P|%D|%c|%m|%G|%l"

# a node's variable inside a generated word; every other character of a word is taken as written
_VAR_OPEN, _VAR_CLOSE = "\ue000", "\ue001"
# NAME, or NAME[@] for each element of an array as its own word
_VAR = re.compile(f"{_VAR_OPEN}([A-Za-z_][A-Za-z0-9_]*(?:\\[@\\])?){_VAR_CLOSE}")
_ENV_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*\Z")
_TIME = re.compile(r"^(?:(\d+)-)?(\d+)(?::(\d+))?(?::(\d+))?\Z")
_GRES_GPU = re.compile(r"(?:^|,)gpu(?::[^:,()]+)?:(\d+)")
_SIZE = re.compile(r"^(\d+)([KMGT]?)\Z", re.IGNORECASE)
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}\Z")
# a key of scontrol's one-line output; values may hold spaces ("Reason=Not responding [slurm@...]")
_FIELD = re.compile(r"(?<!\S)([A-Za-z][A-Za-z0-9_/:]*)=")
# what munge and slurmd log when a credential is refused or cannot be made ("error: Munge decode
# failed: Invalid credential" in slurmd's journal when the node's key is not the controller's): a
# line that names munge or a credential, and an error
_MUNGE = re.compile(r"(?i)munge|credential")
_ERROR = re.compile(r"(?i)\b(?:error|fail\w*|invalid|expired|rewound|replayed|unauthorized)\b")


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


# (job key, lowest, default when not given, what it counts): checked before anything is
# copied or submitted (sbatch would take --nodes=-1 for one node, or refuse in its own words)
_COUNTS = (
    ("nodes", 1, 1, "nodes"),
    ("gpus_per_node", 0, 0, "GPUs per node"),
    ("cpus_per_node", 1, 1, "CPUs per node"),
)


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
    counts = {}
    for key, lowest, default, what in _COUNTS:
        value = job.get(key)
        number = default if value is None or value == "" else parse.as_int(value)
        if number is None or number < lowest:
            errors.append(f"train_{key}: {value!r} is not a count of {what}. Fix: a whole number, {lowest} or more.")
        counts[key] = number if isinstance(number, int) and number >= lowest else default
    gpus, nodes = counts["gpus_per_node"], counts["nodes"]
    if gpus > part["gpus"]:
        errors.append(
            f"train_gpus_per_node: {gpus}, and no node of partition {name} has more than {part['gpus']}. "
            "Fix: ask for fewer per node (and more nodes), or use a partition with bigger nodes."
        )
    if nodes > part["nodes"]:
        errors.append(f"train_nodes: {nodes}, and partition {name} has {part['nodes']}. Fix: ask for fewer nodes.")
    cpus = counts["cpus_per_node"]
    if part["cpus"] and cpus > part["cpus"]:
        errors.append(
            f"train_cpus_per_node: {cpus}, and no node of partition {name} has more than {part['cpus']}. "
            "Fix: ask for fewer."
        )
    memory = job.get("memory")
    if memory:
        mib = memory_mib(memory)
        if mib is None or mib < 1:
            errors.append(f"train_memory: {memory!r} is not a size. Fix: e.g. 64G or 32000 (MiB).")
        elif part["memory_mib"] and mib > part["memory_mib"]:
            errors.append(
                f"train_memory: {memory}, and no node of partition {name} has more than {part['memory_mib']} MiB. "
                "Fix: ask for less."
            )
    bad = [n for n in job.get("env_names") or [] if not _ENV_NAME.match(str(n))]
    if bad:
        errors.append(f"train_env: {', '.join(map(repr, bad))}. Fix: names of variables (letters, digits, underscore).")
    if not _NAME.match(str(job.get("name") or "")):
        errors.append(
            f"train_job_name: {job.get('name')!r}. Fix: letters, digits, dot, dash and underscore, 64 at most."
        )
    return errors


def _clock(seconds: int) -> str:
    days, rest = divmod(int(seconds), 86400)
    text = f"{rest // 3600:02d}:{rest % 3600 // 60:02d}:{rest % 60:02d}"
    return f"{days}-{text}" if days else text


def _key_values(line: str) -> dict:
    """The key=value fields of one line of `scontrol show ... -o`, values with spaces kept whole."""
    keys = list(_FIELD.finditer(line))
    return {
        key.group(1): line[key.end() : keys[i + 1].start() if i + 1 < len(keys) else len(line)].strip()
        for i, key in enumerate(keys)
    }


def parse_scontrol_job(text: str):
    """{"id", "state", "elapsed", "nodes", "reason", "exit_code", "signal", "submitted"} from
    `scontrol show job -o ID` (one line of key=value words), or None. slurmctld knows a job from
    its submission until MinJobAge after its end, wherever scontrol runs."""
    first = (text or "").strip().splitlines()[:1]
    # "Reason=ReqNodeNotAvail, UnavailableNodes:node-2" is one value
    fields = _key_values(first[0]) if first else {}
    if "JobId" not in fields or "JobState" not in fields:
        return None
    code = exit_of(fields.get("ExitCode", "")) or (None, None)
    nodes = fields.get("NodeList", "")
    return {
        "id": fields["JobId"],
        "state": fields["JobState"],
        "elapsed": fields.get("RunTime", ""),
        "nodes": "" if nodes == "(null)" else nodes,
        "reason": fields.get("Reason", ""),
        "exit_code": code[0],
        "signal": code[1],
        "submitted": fields.get("SubmitTime", ""),
    }


def parse_nodes(text: str) -> dict:
    """{name: {"state", "reason"}} from `scontrol show node -o NODES` (one line per node; NODES may
    be a host list such as node-[1-2]). state is Slurm's with its flags (IDLE+COMPLETING+NOT_RESPONDING),
    reason "" when Slurm gives none."""
    out = {}
    for line in (text or "").splitlines():
        fields = _key_values(line.strip())
        if "NodeName" in fields and "State" in fields:
            reason = fields.get("Reason", "")
            reason = "" if reason in ("(null)", "None") else reason
            out[fields["NodeName"]] = {"state": fields["State"], "reason": reason}
    return out


def not_responding(nodes: dict) -> list:
    """The nodes (parse_nodes) slurmctld gets no answer from (sinfo marks them with *)."""
    return sorted(name for name, node in nodes.items() if "NOT_RESPONDING" in node["state"].split("+"))


def stuck_nodes(nodes: dict) -> list:
    """The nodes a COMPLETING job waits on: those of its nodes (parse_nodes) still completing or
    not answering, or all of them when Slurm marks none."""
    flagged = sorted(
        name for name, node in nodes.items() if {"COMPLETING", "NOT_RESPONDING"} & set(node["state"].split("+"))
    )
    return flagged or sorted(nodes)


def epoch(text: str):
    """Seconds since the epoch of a time as Slurm prints it (2026-11-24T13:42:32, the local time of
    the host that reads it), or None."""
    try:
        return int(time.mktime(time.strptime(str(text).strip(), "%Y-%m-%dT%H:%M:%S")))
    except ValueError:
        return None


def munge_errors(journal: str) -> list:
    """The lines of a node's journal (journalctl -u slurmd -u munge) where munge refused or could
    not make a credential."""
    return [line.strip() for line in (journal or "").splitlines() if _MUNGE.search(line) and _ERROR.search(line)]


def stuck_line(job: dict, seconds: int, nodes: list) -> str:
    """What the follow says of a job that has stayed COMPLETING for `seconds` on `nodes`."""
    states = job.get("node_states") or {}
    where = ", ".join(
        f"{name} ({states[name]['state']}{': ' + states[name]['reason'] if states[name]['reason'] else ''})"
        if name in states
        else name
        for name in nodes
    )
    # the job's Reason says why it ended (TimeLimit), when anything; never why it waits
    reason = job.get("reason") if job.get("reason") not in (None, "", "None") else "none"
    return (
        f"job {job.get('id')} has been {COMPLETING} for {seconds} s (Slurm's reason: {reason}): slurmctld waits for "
        f"{where} to end it"
    )


def stuck_message(job: dict, journals: dict) -> str:
    """Why a job stays COMPLETING, for a person: the nodes it waits on (job: the follow's failed
    result, with stuck_nodes, stuck_for and node_states) and what each node's journal says.
    journals: {node: {"text": journalctl's output} or {"error": why it could not be read}}; a node
    with no entry is not a host of the inventory."""
    nodes = job.get("stuck_nodes") or []
    parts = [stuck_line(job, int(job.get("stuck_for") or 0), nodes) + "."]
    refused = []
    for name in nodes:
        read = journals.get(name)
        if read is None:
            parts.append(f"{name} is not a host of the inventory: its journal was not read.")
        elif read.get("error"):
            parts.append(f"{name}'s journal could not be read: {read['error']}.")
        else:
            lines = munge_errors(read.get("text", ""))
            if lines:
                refused.append(name)
                more = f" ({len(lines)} such lines since the job was submitted)" if len(lines) > 1 else ""
                parts.append(f"{name}'s journal (slurmd, munge): {lines[-1]}{more}.")
            else:
                parts.append(f"{name}'s journal (slurmd, munge) says nothing of munge since the job was submitted.")
    if refused:
        parts.append(
            f"Fix: munge refuses credentials between {', '.join(refused)} and the controller: a munge key that is not "
            "the controller's (or clocks far apart: Expired or Rewound credential). Run playbooks/cluster.yml, which "
            "gives every node the controller's key and says which node's key it replaced."
        )
    else:
        where = ", ".join(nodes) or "its nodes"
        parts.append(f"Fix: see journalctl -u slurmd -u munge and scontrol show node on {where}.")
    parts.append(
        f"The job is not cancelled: once slurmctld hears from the node it ends (a job whose launch the node refused is "
        f"requeued and runs again); follow it with train_job_id={job.get('id')}."
    )
    return " ".join(parts)


def exit_of(text: str):
    """(exit code, signal) of Slurm's "code:signal" ExitCode, or None."""
    match = re.match(r"^(\d+):(\d+)\Z", (text or "").strip())
    return (int(match.group(1)), int(match.group(2))) if match else None


def parse_sacct(text: str, job_id: str):
    """The job's own line of `sacct -n -P -o SACCT_FIELDS -j ID` (or `sacct -c`, which reads the
    job completion log): {"id", "state", "exit_code", "signal", "elapsed", "nodes"}, or None. The
    last one: the completion log has a line for each end of a requeued job (NODE_FAIL, then the
    run after it)."""
    found = None
    for line in text.splitlines():
        fields = line.strip().split("|")
        if len(fields) != 5 or fields[0] != str(job_id):
            continue
        code = exit_of(fields[2]) or (None, None)
        found = {
            # "CANCELLED by 0": the state's first word
            "state": fields[1].split()[0] if fields[1] else "",
            "id": fields[0],
            "exit_code": code[0],
            "signal": code[1],
            "elapsed": fields[3],
            "nodes": fields[4],
        }
    return found


def controller_down(scontrol_rc: int, scontrol_err: str) -> bool:
    """Whether scontrol failed because slurmctld did not answer, not because it knows no such
    job: anything but "Invalid job id" counts as not answering (waited out, never called lost)."""
    return scontrol_rc != 0 and "invalid job id" not in (scontrol_err or "").lower()


def status_of(job_id, scontrol_text: str, sacct_text: str, down: str = ""):
    """A job's state: what slurmctld says of it (scontrol), or once it has forgotten the job
    (MinJobAge after its end), what accounting says (sacct). {"id", "state", "elapsed", "nodes",
    "reason", "exit_code", "signal", "finished"}, or None when neither knows it (the job is lost).
    down: why slurmctld did not answer; then the job is not lost, its state is accounting's or
    UNKNOWN, with controller_down set, until slurmctld answers again."""
    live = parse_scontrol_job(scontrol_text)
    if live and live["id"] == str(job_id):
        return dict(live, finished=live["state"] in FINISHED)
    done = parse_sacct(sacct_text or "", job_id)
    if done and done["state"] in FINISHED:
        return dict(done, reason="", finished=True)
    if down:
        last = done or {
            "id": str(job_id),
            "state": "UNKNOWN",
            "elapsed": "",
            "nodes": "",
            "exit_code": None,
            "signal": None,
        }
        return dict(last, reason=f"slurmctld does not answer ({down})", finished=False, controller_down=True)
    return None


def run_dir(name: str, stamp: str) -> str:
    """The directory of one submission (its scripts and the snapshot of the code it runs)."""
    return f"{name}-{stamp}"


def _hex(image_id) -> str:
    """An image id without its algorithm ("sha256:0a45..." -> "0a45..."), as Podman names it."""
    return str(image_id or "").rsplit(":", maxsplit=1)[-1]


def image_file(source: str, runtime: str, image_id: str) -> str:
    """The file name of a job image on the cluster: the team's image name and its id, so that a
    new image never replaces the file a queued job is about to run."""
    suffix = runtimes.runtime(runtime)["image_suffix"]
    return re.sub(r"[^A-Za-z0-9_.-]", "_", source) + f"-{_hex(image_id)[:12]}" + suffix


def _runs_by_id(job: dict) -> bool:
    """Whether the job's nodes run its image by id, loaded from the job image (an archive)."""
    return runtimes.RUNTIMES.get(job.get("runtime"), {}).get("image") == "id"


def complete(job: dict) -> dict:
    """The job as the scripts take it, from what the playbook gives: the image from image_file
    (its path on the cluster) and image_id (the runtimes whose nodes run it by id, loaded from
    the file), the cache mounts of the release when none are given."""
    job = dict(job)
    if _runs_by_id(job):
        job["image"] = _hex(job.get("image_id"))
        job["image_archive"] = job.get("image_file")
    else:
        job["image"] = job.get("image_file")
    if not job.get("mounts"):
        job["mounts"] = releases.RELEASES[job.get("release") or "6.x"]["mounts"]
    return job


def cache_binds(cache: str, mounts: dict) -> list:
    """(host path, container path) of each cache directory of the job's node-local copy."""
    return [(f"{cache}/{sub}", target) for sub, target in sorted(mounts.items())]


def image_path(job: dict):
    """The job image's file on the cluster (complete's job): what the nodes read before it runs."""
    return job.get("image_archive") if _runs_by_id(job) else job.get("image")


def _values(entry: dict, **more) -> dict:
    """What a runtime entry's words are made of (runtimes.py, its templates)."""
    ids = {"job_id": node("SLURM_JOB_ID"), "node_id": node("SLURM_NODEID")}
    container = entry["container"].format(**ids) if entry["container"] else None
    values = {"workdir": WORKDIR, "container": container, "job_gpus": node("JOB_GPUS")}
    values.update(gpu_devices=node("GPU_DEVICES[@]"), **ids)
    values.update(more)
    return values


def _argv(words, values: dict) -> list:
    return [word.format(**values) for word in words]


def runtime_argv(runtime: str, image: str, binds, env_names, command, gpus: bool, rc=None) -> list:
    """The command that runs `command` in the job's image on a node (words of the node script;
    node() marks the node's variables in them). env_names: variables passed from the node's
    environment. The image's own entrypoint is not run, as `apptainer exec` does not run it.

    GPUs: Apptainer's --nv and enroot's hook bring the node's GPUs, and the job's device cgroup
    (Slurm's ConstrainDevices) lets only the job's open; Podman and Docker are given the job's
    GPUs by their numbers on the node (JOB_GPUS, from Slurm's SLURM_STEP_GPUS).

    Apptainer takes the environment's variables from APPTAINERENV_<NAME> (the node script
    exports them; values never appear on a command line), enroot from --env NAME; rc: enroot's
    command script, in place of the image's entrypoint. Each runtime's words: runtimes.RUNTIMES."""
    entry = runtimes.runtime(runtime)
    values = _values(entry)
    argv = _argv(entry["run"], values)
    if rc and entry["rc"]:
        argv.append(entry["rc"]["option"].format(rc=rc))
    argv += _argv(entry["gpus"], values) if gpus else []
    argv += [entry["bind"].format(src=src, dst=dst) for src, dst in binds]
    argv += [entry["env"].format(name=name) for name in env_names] if entry["env"] else []
    return argv + [image] + list(command)


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
        + [f"--rdzv_endpoint={node('MASTER_ADDR')}:{node('MASTER_PORT')}", job["script"]]
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
        # a port per job: two jobs whose first node is the same host do not meet
        f"MASTER_PORT=$(({RENDEZVOUS_PORT} + SLURM_JOB_ID % 1000))",
        "export MASTER_ADDR MASTER_PORT",
        # one task per node; the job fails as soon as one node's training does
        # srun takes the job's CPUs per task only when told (Slurm 22.05 and later)
        "exec srun --kill-on-bad-exit=1 --ntasks-per-node=1 "
        f'--cpus-per-task="$SLURM_CPUS_PER_TASK" bash {shlex.quote(node_script)}',
    ]
    return "\n".join(text) + "\n"


def node_script(job: dict, managed: str = "Ansible managed (isaacsim.fleet)") -> str:
    """What each node runs: the caches in, the training, the caches back (first node), its exit.

    job: name, runtime, image (the SIF or squashfs file, or for podman and docker the image's
    id, with image_archive the file each node loads it from), code_dir (the code this job runs,
    on the shared file system), logs_dir (where its logs/ go, shared by the jobs), cache_dir (the
    shared caches), local_cache (the node's directory for them; a directory per job is made in
    it), mounts ({cache subdirectory: path in the container}), python, script, args,
    gpus_per_node, nodes, env_names."""
    runtime = job["runtime"]
    entry = runtimes.runtime(runtime)
    # the node's own disk (Slurm's per-job $TMPDIR by default); only this job's directory in it
    base = _word(job["local_cache"]) if job.get("local_cache") else '"${TMPDIR:-/tmp}"'
    binds = cache_binds(node("LOCAL_CACHE"), job["mounts"]) + [(job["code_dir"], WORKDIR)]
    if job.get("logs_dir"):
        binds.append((job["logs_dir"], f"{WORKDIR}/logs"))
    env_names = sorted(set(job.get("env_names") or []) | {"CUDA_VISIBLE_DEVICES", "MASTER_ADDR", "MASTER_PORT"})
    env_names += ["SLURM_JOB_ID", "SLURM_NNODES", "SLURM_NODEID"]
    values = _values(entry, image=job["image"], archive=job.get("image_archive"))
    # a runtime that makes a container of the image on each node runs that container
    image = values["container"] if entry["create"] else job["image"]
    rc = f"{node('LOCAL_CACHE')}/{entry['rc']['file']}" if entry["rc"] else None
    gpus = bool(int(job.get("gpus_per_node") or 0))
    run = runtime_argv(runtime, image, binds, env_names, training_command(job), gpus, rc=rc)
    dirs = " ".join(_word(f"{node('LOCAL_CACHE')}/{sub}") for sub in sorted(job["mounts"]))
    text = [
        "#!/bin/bash",
        f"# {managed}",
        "set -o pipefail",
        f"SHARED_CACHE={_word(job['cache_dir'])}",
        f'LOCAL_CACHE={base}/isaac-sim-cache-"$SLURM_JOB_ID"',
        # Isaac Sim reads and writes its caches a lot: the node's disk, not the shared file system
        f'mkdir -p {dirs} && rsync -a "$SHARED_CACHE/" "$LOCAL_CACHE/" 2>/dev/null || true',
        "copy_back() {",
    ]
    if entry["remove_on_exit"]:
        text.append(f"  {line(_argv(entry['remove_on_exit'], values))} >/dev/null 2>&1 || true")
    text += [
        # rsync writes each file beside its place and renames it: a copy cut short, or another
        # job reading meanwhile, never meets a torn file
        '  if [ "$SLURM_NODEID" = 0 ]; then rsync -a "$LOCAL_CACHE/" "$SHARED_CACHE/" || true; fi',
        '  rm -rf "$LOCAL_CACHE"',
        "}",
        "trap copy_back EXIT",
        # the job's GPUs by their numbers on the node (CUDA_VISIBLE_DEVICES counts from 0 in
        # the job's device cgroup)
        'JOB_GPUS="${SLURM_STEP_GPUS:-${SLURM_JOB_GPUS:-}}"',
    ]
    text += entry["gpu_setup"] if gpus else []
    if entry["env_export"]:
        # into the container by the runtime's own prefix
        text += [f'export {entry["env_export"].format(name=name)}="${{{name}:-}}"' for name in env_names]
    if entry["load"] and job.get("image_archive"):
        # the image comes to each node once, from the archive on the shared path; run by its id
        find, load = (line(_argv(words, values)) for words in entry["load"])
        text.append(f"{find} >/dev/null 2>&1 || {load} >/dev/null")
    if entry["rc"]:
        script = entry["rc"]["script"].format(**values)
        text.append("printf '%s\\n' " + shlex.quote(script) + f' > "$LOCAL_CACHE/{entry["rc"]["file"]}"')
    if entry["create"]:
        text.append(f"{line(_argv(entry['create'], values))} >/dev/null")
    # the training runs in the background so that a cancel (scancel's SIGTERM) is handled at
    # once: the container is stopped (Podman's conmon would die with the step and leave it
    # running), then the caches go back, within Slurm's KillWait (30 s by default); bash defers
    # a trap while a foreground command runs
    if entry["stop"]:
        stop = f"  {line(_argv(entry['stop'], values))} >/dev/null 2>&1 || true"
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
    if entry["remove"]:
        text.append(f"{line(_argv(entry['remove'], values))} >/dev/null 2>&1 || true")
    text += ['echo "isaacsim.fleet: training on node $SLURM_NODEID exited with $status"', "exit $status"]
    return "\n".join(text) + "\n"


def build_argv(runtime: str, source_image: str, out: str, archive=None, fakeroot=True) -> list:
    """The command that turns the team's Docker image into what the runtime runs, on the build host
    (runtimes.RUNTIMES: each runtime's build). archive: a `docker save` archive of it, for the
    builds that take one (Apptainer); fakeroot: Apptainer's build without root."""
    return runtimes.runtime(runtime)["build"](source_image, out, archive, fakeroot)


def submitted_id(text: str):
    """The job id of `sbatch --parsable` ("123" or "123;cluster"), or None."""
    first = (text or "").strip().splitlines()[:1]
    job = first[0].split(";", 1)[0] if first else ""
    return job if job.isdigit() else None


def progress_line(job: dict) -> str:
    """One line of a job's progress for a person: state, elapsed, nodes (or why it waits), and
    those of its nodes slurmctld gets no answer from."""
    where = job.get("nodes") or ""
    if job.get("state") == "PENDING" and job.get("reason") not in (None, "", "None"):
        where = f"waiting: {job['reason']}"
    if job.get("not_responding"):
        where = f"{where} - not responding: {', '.join(job['not_responding'])}"
    if job.get("controller_down"):
        where = f"{where} - {job['reason']}; waiting for it".lstrip(" -")
    return f"job {job.get('id')} {job.get('state', '?')} {job.get('elapsed', '')} {where}".rstrip()
