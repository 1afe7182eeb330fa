"""Training jobs on Slurm: time limits, what the cluster says (sinfo, squeue, sacct lines as
Slurm 22.05 prints them), request checks, and the scripts, run by a real bash against a
recording stand-in for the container runtime."""

import os
import signal
import stat
import subprocess
import time

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import releases
from ansible_collections.isaacsim.fleet.plugins.module_utils.train import slurm


@pytest.mark.parametrize(
    "text, seconds",
    [
        ("30", 1800),
        ("30:15", 1815),
        ("23:00:00", 82800),
        ("2-12", 2 * 86400 + 12 * 3600),
        ("1-02:03", 86400 + 2 * 3600 + 3 * 60),
        ("1-02:03:04", 86400 + 2 * 3600 + 3 * 60 + 4),
        ("UNLIMITED", 0),
        ("infinite", 0),
        ("abc", None),
        ("1:2:3:4", None),
        ("-5", None),
        ("", None),
    ],
)
def test_slurm_time_limits(text, seconds):
    assert slurm.parse_time(text) == seconds


def test_memory_sizes_are_mib_as_slurm_counts_them():
    assert [slurm.memory_mib(s) for s in ("32000", "64G", "512m", "1T", "2048K", "lots")] == [
        32000,
        65536,
        512,
        1048576,
        2,
        None,
    ]


SINFO = """gpu*|2|2|2000|gpu:2|infinite
gpu*|1|2|2000|gpu:1|infinite
big|1|64|512000|gpu:a100:4(S:0-1)|2-00:00:00
cpu|3|16|64000|(null)|1:00:00
"""


def test_partitions_from_sinfo():
    parts = slurm.parse_sinfo(SINFO)
    assert parts["gpu"] == {"default": True, "nodes": 3, "cpus": 2, "memory_mib": 2000, "gpus": 2, "max_time": 0}
    assert parts["big"]["gpus"] == 4 and parts["big"]["max_time"] == 2 * 86400 and not parts["big"]["default"]
    assert parts["cpu"]["gpus"] == 0 and parts["cpu"]["nodes"] == 3


JOB = {"name": "train-ant", "partition": "gpu", "time": "01:00:00", "gpus_per_node": 2, "nodes": 1}


def test_a_request_the_cluster_can_run_passes_and_the_default_partition_is_taken_when_none_is_named():
    parts = slurm.parse_sinfo(SINFO)
    assert slurm.check_request(JOB, parts) == []
    assert slurm.check_request(dict(JOB, partition=None), parts) == []


def test_a_request_the_cluster_cannot_run_is_refused_naming_the_variable():
    parts = slurm.parse_sinfo(SINFO)

    def errors(**over):
        return " ".join(slurm.check_request(dict(JOB, **over), parts))

    assert "train_partition: 'nope' is not a partition of the cluster. Fix: one of big, cpu, gpu." in errors(
        partition="nope"
    )
    assert "train_gpus_per_node: 3, and no node of partition gpu has more than 2" in errors(gpus_per_node=3)
    assert "train_time: 'abc' does not parse as a Slurm time" in errors(time="abc")
    assert "train_time: 3-00:00:00 is longer than partition big allows (2-00:00:00)" in errors(
        partition="big", time="3-00:00:00", gpus_per_node=1
    )
    assert "train_nodes: 4, and partition gpu has 3" in errors(nodes=4)
    assert "train_memory: '2 gigs' is not a size" in errors(memory="2 gigs")
    assert "train_memory: 4G, and no node of partition gpu has more than 2000 MiB" in errors(memory="4G")
    assert "train_cpus_per_node: 8" in errors(cpus_per_node=8)
    assert "train_job_name: 'my job'" in errors(name="my job")
    assert slurm.check_request(JOB, {}) == [
        "train_partition: the cluster reports no partition (sinfo). Fix: check that slurmctld answers."
    ]


def test_counts_out_of_range_are_refused_before_anything_is_copied():
    parts = slurm.parse_sinfo(SINFO)

    def errors(**over):
        return " ".join(slurm.check_request(dict(JOB, **over), parts))

    # -1 and 0 nodes once ran a one-node job without a word
    assert "train_nodes: -1 is not a count of nodes. Fix: a whole number, 1 or more." in errors(nodes=-1)
    assert "train_nodes: 0 is not a count of nodes" in errors(nodes=0)
    assert "train_gpus_per_node: -2 is not a count of GPUs per node" in errors(gpus_per_node=-2)
    assert "train_cpus_per_node: -4 is not a count of CPUs per node" in errors(cpus_per_node=-4)
    assert "train_cpus_per_node: 0 is not a count" in errors(cpus_per_node=0)
    assert "train_nodes: 'two' is not a count" in errors(nodes="two")
    assert "train_nodes: 1.5 is not a count" in errors(nodes=1.5)
    assert "train_memory: '0' is not a size" in errors(memory="0")
    assert "train_memory: '-5G' is not a size" in errors(memory="-5G")
    # given as text (-e train_nodes=2) they are numbers all the same; none given is the default
    assert errors(nodes="2", gpus_per_node="0", cpus_per_node="1") == ""
    assert errors(nodes=None, gpus_per_node=None) == ""


# `scontrol show job -o 17` (Slurm 22.05), shortened to the words read and a few around them
SCONTROL_RUNNING = (
    "JobId=17 JobName=train-ant UserId=root(0) GroupId=root(0) MCS_label=N/A Priority=1 Nice=0 "
    "Account=(null) QOS=(null) JobState=RUNNING Reason=None Dependency=(null) Requeue=1 Restarts=0 "
    "BatchFlag=1 Reboot=0 ExitCode=0:0 RunTime=00:01:02 TimeLimit=00:10:00 TimeMin=N/A "
    "NodeList=node-[1-2] BatchHost=node-1 NumNodes=2 NumCPUs=2 NumTasks=2 CPUs/Task=1\n"
)
SCONTROL_PENDING = (
    "JobId=18 JobName=train-ant JobState=PENDING Reason=Resources Dependency=(null) ExitCode=0:0 "
    "RunTime=00:00:00 TimeLimit=00:10:00 NodeList=(null) NumNodes=1\n"
)
SCONTROL_FAILED = SCONTROL_RUNNING.replace(
    "JobState=RUNNING Reason=None", "JobState=FAILED Reason=NonZeroExitCode"
).replace("ExitCode=0:0", "ExitCode=3:0")


def test_what_scontrol_and_sacct_say_of_a_job():
    assert slurm.parse_scontrol_job(SCONTROL_RUNNING) == {
        "id": "17",
        "state": "RUNNING",
        "elapsed": "00:01:02",
        "nodes": "node-[1-2]",
        "reason": "None",
        "exit_code": 0,
        "signal": 0,
        "submitted": "",
    }
    assert slurm.parse_scontrol_job(SCONTROL_PENDING)["nodes"] == ""
    assert slurm.parse_scontrol_job("slurm_load_jobs error: Invalid job id specified") is None
    sacct = "2|FAILED|3:0|00:00:12|node-1\n2.batch|FAILED|3:0|00:00:12|node-1\n3|CANCELLED by 0|0:15|00:01:00|node-2\n"
    assert slurm.parse_sacct(sacct, "2") == {
        "id": "2",
        "state": "FAILED",
        "exit_code": 3,
        "signal": 0,
        "elapsed": "00:00:12",
        "nodes": "node-1",
    }
    cancelled = slurm.parse_sacct(sacct, "3")
    assert (cancelled["state"], cancelled["exit_code"], cancelled["signal"]) == ("CANCELLED", 0, 15)
    assert slurm.parse_sacct(sacct, "9") is None
    assert "CANCELLED" in slurm.FINISHED and "RUNNING" not in slurm.FINISHED


def test_one_gpu_runs_python_and_more_run_torchrun_with_one_process_per_gpu():
    job = {"script": "scripts/train.py", "args": ["--task=Ant", "--headless"], "gpus_per_node": 1}
    assert slurm.training_command(job) == ["/isaac-sim/python.sh", "scripts/train.py", "--task=Ant", "--headless"]
    multi = slurm.training_command(dict(job, gpus_per_node=4, nodes=2, python="/workspace/isaaclab/isaaclab.sh -p"))
    multi = [slurm.shown(w) for w in multi]
    assert multi[:4] == ["/workspace/isaaclab/isaaclab.sh", "-p", "-m", "torch.distributed.run"]
    assert "--nproc_per_node=4" in multi and "--nnodes=$SLURM_NNODES" in multi
    assert "--rdzv_endpoint=$MASTER_ADDR:$MASTER_PORT" in multi and multi[-3:] == [
        "scripts/train.py",
        "--task=Ant",
        "--headless",
    ]


def test_the_batch_script_asks_for_the_resources_and_starts_one_task_per_node():
    job = dict(
        JOB,
        nodes=2,
        cpus_per_node=16,
        memory="64G",
        account="lab",
        modules=["eth_proxy", "apptainer/1.3"],
        log_dir="/shared/jobs/train-ant/logs",
        sbatch_options=["--mail-type=END"],
    )
    text = slurm.batch_script(job, "/shared/jobs/train-ant/node.sh")
    for directive in (
        "#SBATCH --job-name=train-ant",
        "#SBATCH --nodes=2",
        "#SBATCH --cpus-per-task=16",
        "#SBATCH --gpus-per-node=2",
        "#SBATCH --mem=64G",
        "#SBATCH --time=01:00:00",
        "#SBATCH --partition=gpu",
        "#SBATCH --account=lab",
        "#SBATCH --output=/shared/jobs/train-ant/logs/slurm-%j.out",
        "#SBATCH --mail-type=END",
        "module load eth_proxy",
        "module load apptainer/1.3",
    ):
        assert directive + "\n" in text, directive
    # srun is told the CPUs per task (Slurm 22.05 no longer passes sbatch's on); a port per job
    assert text.rstrip().endswith(
        'exec srun --kill-on-bad-exit=1 --ntasks-per-node=1 --cpus-per-task="$SLURM_CPUS_PER_TASK" '
        "bash /shared/jobs/train-ant/node.sh"
    )
    assert "MASTER_PORT=$((29500 + SLURM_JOB_ID % 1000))\n" in text
    assert subprocess.run(["bash", "-n"], input=text, text=True, check=False).returncode == 0


@pytest.fixture()
def node(tmp_path):
    """A node: a shared cache with something in it, $TMPDIR, and a recording `apptainer`."""
    shared = tmp_path / "shared-cache"
    (shared / "cache/ov").mkdir(parents=True)
    (shared / "cache/ov/shaders").write_text("warm")
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    fake = bin_dir / "apptainer"
    fake.write_text(
        "#!/bin/bash\n"
        'printf "%s\\n" "$@" > "$RECORD"\n'
        'env | grep ^APPTAINERENV_ | sort > "$RECORD.env"\n'
        'cache=$(printf "%s\\n" "$@" | sed -n "s|^--bind=\\(.*\\)/cache/ov:/root/.cache/ov:rw$|\\1|p")\n'
        'echo more >> "$cache/cache/ov/shaders"\n'
        'exit "${FAKE_EXIT:-0}"\n'
    )
    fake.chmod(fake.stat().st_mode | stat.S_IEXEC)
    # podman: each call's words on a line of their own file (run, image inspect, load, stop, rm)
    podman = bin_dir / "podman"
    podman.write_text(
        "#!/bin/bash\n"
        'printf "%s\\n" "$@" > "$RECORD.podman-$1-$2"\n'
        '[ "$1 $2" = "image inspect" ] && exit "${FAKE_IMAGE_MISSING:-0}"\n'
        # a long run ends when the container is stopped
        'cache=$(printf "%s\\n" "$@" | sed -n "s|^--volume=\\(.*\\)/cache/ov:/root/.cache/ov:rw$|\\1|p")\n'
        '[ "$1" = run ] && [ -n "$cache" ] && echo "$SLURM_JOB_ID" >> "$cache/cache/ov/shaders"\n'
        '[ "$1" = run ] && [ -n "$FAKE_RUN_SECONDS" ] && echo $$ > "$RECORD.pid" && exec sleep "$FAKE_RUN_SECONDS"\n'
        '[ "$1" = stop ] && kill "$(cat "$RECORD.pid")"\n'
        '[ "$1" = run ] && exit "${FAKE_EXIT:-0}"\n'
        "exit 0\n"
    )
    podman.chmod(podman.stat().st_mode | stat.S_IEXEC)
    (tmp_path / "tmp").mkdir()
    env = dict(
        os.environ,
        PATH=f"{bin_dir}:{os.environ['PATH']}",
        RECORD=str(tmp_path / "argv"),
        TMPDIR=str(tmp_path / "tmp"),
        SLURM_JOB_ID="41",
        SLURM_NODEID="0",
        SLURM_NNODES="1",
        MASTER_ADDR="node-1",
        CUDA_VISIBLE_DEVICES="0",
    )
    return tmp_path, env


def bash(script, env):
    return subprocess.run(["bash", str(script)], env=env, capture_output=True, text=True, check=False)


def job_on(tmp_path, **over):
    job = dict(
        name="train-ant",
        runtime="apptainer",
        image="/shared/images/isaac-lab.sif",
        code_dir="/shared/jobs/train-ant/code",
        cache_dir=f"{tmp_path}/shared-cache",
        mounts=releases.RELEASES["4.x"]["mounts"],
        script="scripts/train.py",
        args=["--task=Isaac-Ant-v0", '--note=it\'s a "test" $HOME', "--headless"],
        gpus_per_node=1,
    )
    return dict(job, **over)


def test_a_node_runs_the_training_with_its_words_intact_and_brings_the_caches_back(node):
    tmp_path, env = node
    script = tmp_path / "node.sh"
    script.write_text(slurm.node_script(job_on(tmp_path)))
    done = bash(script, env)
    assert done.returncode == 0, done.stderr
    argv = (tmp_path / "argv").read_text().splitlines()
    # every word of the training reached the runtime as written: nothing expanded, nothing split
    assert argv[-6:] == [
        "/shared/images/isaac-lab.sif",
        "/isaac-sim/python.sh",
        "scripts/train.py",
        "--task=Isaac-Ant-v0",
        '--note=it\'s a "test" $HOME',
        "--headless",
    ]
    assert argv[:5] == ["exec", "--containall", "--writable-tmpfs", "--pwd=/workspace/isaaclab", "--nv"]
    local = f"{tmp_path}/tmp/isaac-sim-cache-41"
    assert f"--bind={local}/cache/ov:/root/.cache/ov:rw" in argv
    assert "--bind=/shared/jobs/train-ant/code:/workspace/isaaclab:rw" in argv
    # the environment by Apptainer's prefix, never on the command line
    assert not [w for w in argv if w.startswith("--env")]
    passed = (tmp_path / "argv.env").read_text().splitlines()
    assert "APPTAINERENV_CUDA_VISIBLE_DEVICES=0" in passed and "APPTAINERENV_SLURM_JOB_ID=41" in passed
    # the node-local copy started warm, came back to the shared cache, and is gone from the node
    assert (tmp_path / "shared-cache/cache/ov/shaders").read_text() == "warmmore\n"
    assert not os.path.exists(local)
    assert "training on node 0 exited with 0" in done.stdout


def test_a_failing_training_is_the_job_s_exit_and_only_the_first_node_writes_the_caches_back(node):
    tmp_path, env = node
    script = tmp_path / "node.sh"
    script.write_text(slurm.node_script(job_on(tmp_path)))
    done = bash(script, dict(env, FAKE_EXIT="3"))
    assert done.returncode == 3
    assert (tmp_path / "shared-cache/cache/ov/shaders").read_text() == "warmmore\n"
    second = bash(script, dict(env, SLURM_NODEID="1"))
    assert second.returncode == 0
    assert (tmp_path / "shared-cache/cache/ov/shaders").read_text() == "warmmore\n"


def test_each_runtime_gets_its_own_command():
    binds, env = [("/l/cache/ov", "/root/.cache/ov")], ["CUDA_VISIBLE_DEVICES"]
    podman = [slurm.shown(w) for w in slurm.runtime_argv("podman", "0a45", binds, env, ["python"], gpus=True)]
    assert podman[:3] == ["podman", "run", "--rm"] and "$GPU_DEVICES[@]" in podman
    # the image's entrypoint does not run (apptainer exec runs none); the job's cgroup holds
    assert "--entrypoint=" in podman and "--cgroups=disabled" in podman
    assert "--volume=/l/cache/ov:/root/.cache/ov:rw" in podman and podman[-2:] == ["0a45", "python"]
    docker = [slurm.shown(w) for w in slurm.runtime_argv("docker", "0a45", binds, env, ["python"], gpus=True)]
    assert '--gpus="device=$JOB_GPUS"' in docker and "--cgroups=disabled" not in docker
    assert "--nv" not in slurm.runtime_argv("apptainer", "x.sif", binds, env, ["python"], gpus=False)
    assert not any("GPU" in w for w in slurm.runtime_argv("podman", "0a45", binds, env, ["python"], gpus=False))
    enroot = slurm.runtime_argv("enroot", "isaaclab-x", binds, env, ["python"], gpus=True)
    assert enroot[:3] == ["enroot", "start", "--rw"] and "--mount=/l/cache/ov:/root/.cache/ov" in enroot
    with pytest.raises(ValueError):
        slurm.runtime_argv("singularity-ce", "x", [], [], [], gpus=False)


def test_a_podman_node_loads_the_image_once_and_gets_the_job_s_gpus_by_their_cdi_names(node):
    tmp_path, env = node
    script = tmp_path / "node.sh"
    job = job_on(tmp_path, runtime="podman", image="0a45aa", image_archive="/shared/images/lab.tar", gpus_per_node=2)
    script.write_text(slurm.node_script(job))
    # Slurm's numbers of the node's GPUs given to this step; CUDA counts from 0 inside the job
    done = bash(script, dict(env, SLURM_STEP_GPUS="1,3", CUDA_VISIBLE_DEVICES="0,1", FAKE_IMAGE_MISSING="1"))
    assert done.returncode == 0, done.stderr
    run = (tmp_path / "argv.podman-run---rm").read_text().splitlines()
    assert [w for w in run if w.startswith("--device=")] == ["--device=nvidia.com/gpu=1", "--device=nvidia.com/gpu=3"]
    assert "--name=train-41-0" in run and "0a45aa" in run
    assert (tmp_path / "argv.podman-load--q").read_text().split() == ["load", "-q", "-i", "/shared/images/lab.tar"]
    # the container is removed whatever the training's end
    assert (tmp_path / "argv.podman-rm--f").read_text().split() == ["rm", "-f", "train-41-0"]
    for f in tmp_path.glob("argv.podman-*"):
        f.unlink()
    # loaded already: no second load
    assert bash(script, dict(env, SLURM_STEP_GPUS="0")).returncode == 0
    assert not (tmp_path / "argv.podman-load--q").exists()


def test_a_cancelled_job_stops_its_container_and_still_brings_the_caches_back(node):
    tmp_path, env = node
    script = tmp_path / "node.sh"
    script.write_text(slurm.node_script(job_on(tmp_path, runtime="podman", image="0a45aa")))
    running = subprocess.Popen(["bash", str(script)], env=dict(env, FAKE_RUN_SECONDS="30"), text=True)
    deadline = time.monotonic() + 10
    while not (tmp_path / "argv.podman-run---rm").exists():
        assert time.monotonic() < deadline
        time.sleep(0.05)
    # what scancel does first: SIGTERM to the step's processes
    running.send_signal(signal.SIGTERM)
    assert running.wait(timeout=10) == 143
    assert (tmp_path / "argv.podman-stop--t").read_text().split() == ["stop", "-t", "10", "train-41-0"]
    assert (tmp_path / "argv.podman-rm--f").exists()
    # what the training wrote to its cache before the cancel is in the shared cache
    assert (tmp_path / "shared-cache/cache/ov/shaders").read_text() == "warm41\n"
    assert not os.path.exists(f"{tmp_path}/tmp/isaac-sim-cache-41")


def test_the_image_becomes_what_the_runtime_runs():
    assert slurm.build_argv("apptainer", "isaac-lab:2.1", "/s/isaac-lab.sif") == [
        "apptainer",
        "build",
        "--force",
        "--fakeroot",
        "/s/isaac-lab.sif",
        "docker-daemon://isaac-lab:2.1",
    ]
    # Apptainer's docker-daemon source needs a tag; a registry's port is not one
    assert (
        slurm.build_argv("apptainer", "reg:5000/isaac-lab", "/s/i.sif")[-1]
        == "docker-daemon://reg:5000/isaac-lab:latest"
    )
    assert slurm.build_argv("apptainer", "x", "/s/i.sif", archive="/tmp/i.tar", fakeroot=False)[-1] == (
        "docker-archive:/tmp/i.tar"
    )
    assert slurm.build_argv("enroot", "isaac-lab:2.1", "/s/i.sqsh") == [
        "enroot",
        "import",
        "--output",
        "/s/i.sqsh",
        "dockerd://isaac-lab:2.1",
    ]
    # Podman loads Docker's archives; the team's image is in its Docker
    assert slurm.build_argv("podman", "isaac-lab:2.1", "/s/i.tar") == [
        "docker",
        "save",
        "--output",
        "/s/i.tar",
        "isaac-lab:2.1",
    ]


def test_podman_and_enroot_nodes_take_the_image_from_the_shared_path():
    job = job_on("/x", runtime="podman", image="0a45aa", image_archive="/shared/images/isaac-lab.tar")
    text = slurm.node_script(job)
    assert "podman image inspect 0a45aa >/dev/null 2>&1 || podman load -q -i /shared/images/isaac-lab.tar" in text
    enroot = slurm.node_script(job_on("/x", runtime="enroot", image="/shared/images/isaac-lab.sqsh"))
    name = 'isaaclab-"${SLURM_JOB_ID}"-"${SLURM_NODEID}"'
    assert f"enroot create --force --name {name} /shared/images/isaac-lab.sqsh" in enroot
    # enroot runs the image's entrypoint unless its command script is replaced
    rc = "printf '%s\\n' 'cd /workspace/isaaclab && exec \"$@\"' > \"$LOCAL_CACHE/.enroot-rc\""
    assert rc in enroot
    assert 'enroot start --rw --rc="${LOCAL_CACHE}"/.enroot-rc ' in enroot
    for script in (text, enroot):
        assert subprocess.run(["bash", "-n"], input=script, text=True, check=False).returncode == 0


def test_submission_ids():
    assert [slurm.submitted_id(t) for t in ("123\n", "77;lab-cluster", "sbatch: error: x", "")] == [
        "123",
        "77",
        None,
        None,
    ]


def test_progress_says_where_a_job_runs_or_why_it_waits():
    running = slurm.parse_scontrol_job(SCONTROL_RUNNING)
    assert slurm.progress_line(running) == "job 17 RUNNING 00:01:02 node-[1-2]"
    pending = slurm.parse_scontrol_job(SCONTROL_PENDING)
    assert slurm.progress_line(pending) == "job 18 PENDING 00:00:00 waiting: Resources"


def test_a_job_is_read_from_slurmctld_then_from_accounting():
    assert slurm.status_of("17", SCONTROL_RUNNING, "")["finished"] is False
    failed = slurm.status_of("17", SCONTROL_FAILED, "")
    assert failed["finished"] and (failed["exit_code"], failed["signal"]) == (3, 0)
    # forgotten by slurmctld (MinJobAge): the completion record
    done = slurm.status_of(
        "17", "slurm_load_jobs error: Invalid job id specified", "17|COMPLETED|0:0|00:00:14|node-1\n"
    )
    assert done["finished"] and done["exit_code"] == 0 and done["nodes"] == "node-1"
    assert slurm.status_of("43", "", "") is None


def test_a_job_is_never_lost_while_slurmctld_does_not_answer():
    # scontrol (22.05) while slurmctld is stopped, and for a job it does not know
    down = "slurm_load_jobs error: Unable to contact slurm controller (connect failure)"
    assert slurm.controller_down(1, down) and not slurm.controller_down(1, "slurm_load_jobs error: Invalid job id")
    assert not slurm.controller_down(0, "")
    # accounting still answers (slurmdbd): its state, said to be accounting's
    running = slurm.status_of("15", "", "15|RUNNING|0:0|00:00:40|node-1\n", down)
    assert running["state"] == "RUNNING" and not running["finished"] and running["controller_down"]
    assert slurm.progress_line(running) == (
        f"job 15 RUNNING 00:00:40 node-1 - slurmctld does not answer ({down}); waiting for it"
    )
    # nothing answers: unknown, not lost
    unknown = slurm.status_of("15", "", "", down)
    assert unknown["state"] == "UNKNOWN" and unknown["controller_down"] and not unknown["finished"]
    # a finished job in accounting is finished whether slurmctld answers or not
    assert slurm.status_of("15", "", "15|COMPLETED|0:0|00:01:10|node-1\n", down)["finished"]


def test_each_submission_has_its_directory_and_the_image_file_names_its_id():
    assert slurm.run_dir("train-ant", "20261124-101500-5f0c") == "train-ant-20261124-101500-5f0c"
    podman = slurm.complete({"runtime": "podman", "image_file": "/s/i.tar", "image_id": "sha256:0a45"})
    assert (podman["image"], podman["image_archive"]) == ("0a45", "/s/i.tar")
    assert podman["mounts"] == releases.RELEASES["6.x"]["mounts"]
    apptainer = slurm.complete({"runtime": "apptainer", "image_file": "/s/i.sif", "release": "4.x"})
    assert apptainer["image"] == "/s/i.sif" and apptainer["mounts"]["cache/ov"] == "/root/.cache/ov"
    name = slurm.image_file("nvcr.io/team/isaac-lab:2.1", "apptainer", "sha256:0a45aaed62e1252814f0")
    assert name == "nvcr.io_team_isaac-lab_2.1-0a45aaed62e1.sif"


def test_variables_passed_into_the_container_must_be_names():
    partitions = slurm.parse_sinfo("gpu*|2|16|64000|gpu:4|1-00:00:00\n")
    job = {"name": "x", "time": "10", "env_names": ["WANDB_API_KEY", "https_proxy", "A-B", "X=1"]}
    assert slurm.check_request(job, partitions) == [
        "train_env: 'A-B', 'X=1'. Fix: names of variables (letters, digits, underscore)."
    ]


# recorded on the cluster scenario (Slurm 22.05.8, systemd 252) with slurm-node-2's munge key
# replaced by another: a job sent there went COMPLETING at once and stayed so, Reason=None, until
# slurmctld set the node DOWN about 8 minutes later and requeued the job
SCONTROL_COMPLETING = (
    "JobId=3 JobName=wrap UserId=root(0) GroupId=root(0) MCS_label=N/A Priority=4294901757 Nice=0 Account=(null) "
    "QOS=(null) JobState=COMPLETING Reason=None Dependency=(null) Requeue=1 Restarts=1 BatchFlag=2 Reboot=0 "
    "ExitCode=0:0 RunTime=00:00:00 TimeLimit=UNLIMITED TimeMin=N/A SubmitTime=2026-11-24T13:42:32 "
    "EligibleTime=2026-11-24T13:42:32 AccrueTime=2026-11-24T13:42:32 StartTime=2026-11-24T13:48:43 EndTime=Unknown "
    "Partition=gpu AllocNode:Sid=slurm-ctl:4465 ReqNodeList=slurm-node-2 ExcNodeList=(null) NodeList=slurm-node-2 "
    "BatchHost=slurm-node-2 NumNodes=1 NumCPUs=1 NumTasks=1 CPUs/Task=1 ReqB:S:C:T=0:0:*:* "
    "TRES=cpu=1,mem=4G,node=1,billing=1 Socks/Node=* NtasksPerN:B:S:C=0:0:*:* CoreSpec=*\n"
)
NODE_COMPLETING = (
    "NodeName=slurm-node-2 Arch=x86_64 CoresPerSocket=2  CPUAlloc=0 CPUEfctv=2 CPUTot=2 CPULoad=1.08 "
    "AvailableFeatures=(null) ActiveFeatures=(null) Gres=gpu:1 NodeAddr=172.17.0.4 NodeHostName=slurm-node-2 "
    "Version=22.05.8 OS=Linux 6.18.44-fc-v595 #1 SMP PREEMPT_DYNAMIC @0  RealMemory=20009 AllocMem=0 FreeMem=21745 "
    "Sockets=1 Boards=1 State=IDLE+COMPLETING+NOT_RESPONDING ThreadsPerCore=1 TmpDisk=0 Weight=1 Owner=N/A "
    "MCS_label=N/A Partitions=gpu  BootTime=2026-11-24T05:30:34 SlurmdStartTime=2026-11-24T13:36:30 "
    "LastBusyTime=2026-11-24T13:42:33 CfgTRES=cpu=2,mem=20009M,billing=2 AllocTRES= CapWatts=n/a CurrentWatts=0 "
    "AveWatts=0 ExtSensorsJoules=n/s ExtSensorsWatts=0 ExtSensorsTemp=n/s\n"
)
NODE_DOWN = (
    NODE_COMPLETING.replace("State=IDLE+COMPLETING+NOT_RESPONDING", "State=DOWN+NOT_RESPONDING").rstrip("\n")
    + " Reason=Not responding [slurm@2026-11-24T13:50:22]\n"
)
NODE_IDLE = NODE_COMPLETING.replace("slurm-node-2", "slurm-node-1").replace("IDLE+COMPLETING+NOT_RESPONDING", "IDLE")
# journalctl -u slurmd -u munge --output=short-iso on slurm-node-2: the key replaced, munge restarted,
# then the job's launch refused (the _print_cred lines follow each error)
JOURNAL = "".join(
    f"2026-11-24T{line}\n"
    for line in (
        "13:42:30+0000 slurm-node-2 systemd[1]: Stopping munge.service - MUNGE authentication service...",
        "13:42:30+0000 slurm-node-2 systemd[1]: munge.service: Deactivated successfully.",
        "13:42:30+0000 slurm-node-2 systemd[1]: Started munge.service - MUNGE authentication service.",
        "13:42:33+0000 slurm-node-2 slurmd[1615]: slurmd-slurm-node-2: error: Munge decode failed: Invalid credential",
        "13:42:33+0000 slurm-node-2 slurmd[1615]: slurmd-slurm-node-2: auth/munge: _print_cred: ENCODED: Thu Jan 01 "
        "00:00:00 1970",
        "13:42:33+0000 slurm-node-2 slurmd[1615]: slurmd-slurm-node-2: auth/munge: _print_cred: DECODED: Thu Jan 01 "
        "00:00:00 1970",
        "13:44:22+0000 slurm-node-2 slurmd[1615]: slurmd-slurm-node-2: error: Munge decode failed: Invalid credential",
    )
)
REFUSED = "slurmd-slurm-node-2: error: Munge decode failed: Invalid credential"


def test_what_scontrol_says_of_a_job_stuck_in_completing_and_of_its_node():
    job = slurm.parse_scontrol_job(SCONTROL_COMPLETING)
    assert (job["state"], job["nodes"], job["reason"], job["submitted"]) == (
        "COMPLETING",
        "slurm-node-2",
        "None",
        "2026-11-24T13:42:32",
    )
    assert not slurm.status_of("3", SCONTROL_COMPLETING, "")["finished"]
    # a reason with spaces is one value, not its first word
    waiting = SCONTROL_COMPLETING.replace(
        "JobState=COMPLETING Reason=None", "JobState=PENDING Reason=ReqNodeNotAvail, UnavailableNodes:slurm-node-2"
    )
    assert slurm.parse_scontrol_job(waiting)["reason"] == "ReqNodeNotAvail, UnavailableNodes:slurm-node-2"
    nodes = slurm.parse_nodes(NODE_COMPLETING + NODE_IDLE)
    assert nodes == {
        "slurm-node-2": {"state": "IDLE+COMPLETING+NOT_RESPONDING", "reason": ""},
        "slurm-node-1": {"state": "IDLE", "reason": ""},
    }
    assert slurm.parse_nodes(NODE_DOWN)["slurm-node-2"] == {
        "state": "DOWN+NOT_RESPONDING",
        "reason": "Not responding [slurm@2026-11-24T13:50:22]",
    }
    assert slurm.parse_nodes("Node slurm-node-9 not found\n") == {}
    assert slurm.not_responding(nodes) == ["slurm-node-2"]
    # the nodes a completing job waits for: those Slurm marks, else all of the job's
    assert slurm.stuck_nodes(nodes) == ["slurm-node-2"]
    both = {"a": {"state": "MIXED", "reason": ""}, "b": {"state": "IDLE", "reason": ""}}
    assert slurm.stuck_nodes(both) == ["a", "b"]


def test_slurm_times_are_seconds_of_the_host_that_reads_them(monkeypatch):
    monkeypatch.setenv("TZ", "UTC")
    time.tzset()
    try:
        assert slurm.epoch("2026-11-24T13:42:32") == 1795527752
        assert slurm.epoch("Unknown") is None and slurm.epoch("") is None
    finally:
        monkeypatch.delenv("TZ")
        time.tzset()


def test_a_munge_credential_refused_is_found_in_the_node_s_journal():
    assert slurm.munge_errors(JOURNAL) == [
        f"2026-11-24T13:42:33+0000 slurm-node-2 slurmd[1615]: {REFUSED}",
        f"2026-11-24T13:44:22+0000 slurm-node-2 slurmd[1615]: {REFUSED}",
    ]
    # munged that cannot start, a credential expired (clocks apart): errors too
    assert slurm.munge_errors(
        'x munged[9]: munged: Error: Keyfile is insecure: "/etc/munge/munge.key" should not be readable by other\n'
        "x slurmd[9]: error: Munge decode failed: Expired credential\n"
        "x systemd[1]: Started munge.service - MUNGE authentication service.\n"
    ) == [
        'x munged[9]: munged: Error: Keyfile is insecure: "/etc/munge/munge.key" should not be readable by other',
        "x slurmd[9]: error: Munge decode failed: Expired credential",
    ]


def stuck(**over):
    job = slurm.status_of("3", SCONTROL_COMPLETING, "")
    job.update(node_states=slurm.parse_nodes(NODE_COMPLETING), stuck_nodes=["slurm-node-2"], stuck_for=31)
    job.update(over)
    return job


def test_a_job_stuck_in_completing_names_its_node_its_state_and_what_its_journal_says():
    assert slurm.stuck_line(stuck(), 31, ["slurm-node-2"]) == (
        "job 3 has been COMPLETING for 31 s (Slurm's reason: none): slurmctld waits for slurm-node-2 "
        "(IDLE+COMPLETING+NOT_RESPONDING) to end it"
    )
    # ended at its time limit (measured: Reason=TimeLimit while it waits)
    assert slurm.stuck_line(stuck(reason="TimeLimit"), 31, ["slurm-node-2"]).startswith(
        "job 3 has been COMPLETING for 31 s (Slurm's reason: TimeLimit): slurmctld waits for slurm-node-2 ("
    )
    text = slurm.stuck_message(stuck(), {"slurm-node-2": {"text": JOURNAL}})
    assert text.startswith("job 3 has been COMPLETING for 31 s (Slurm's reason: none): slurmctld waits for slurm-")
    last = f"2026-11-24T13:44:22+0000 slurm-node-2 slurmd[1615]: {REFUSED}"
    assert f"slurm-node-2's journal (slurmd, munge): {last} (2 such lines since the job was submitted)." in text
    assert "Fix: munge refuses credentials between slurm-node-2 and the controller" in text
    assert "Run playbooks/cluster.yml" in text
    assert text.endswith(
        "The job is not cancelled: once slurmctld hears from the node it ends (a job whose launch the node refused is "
        "requeued and runs again); follow it with train_job_id=3."
    )
    # a down node's reason is named with its state
    down = stuck(node_states=slurm.parse_nodes(NODE_DOWN))
    assert "slurm-node-2 (DOWN+NOT_RESPONDING: Not responding [slurm@2026-11-24T13:50:22])" in slurm.stuck_line(
        down, 31, ["slurm-node-2"]
    )


def test_a_stuck_job_s_node_whose_journal_says_nothing_or_cannot_be_read_is_still_named():
    quiet = slurm.stuck_message(stuck(), {"slurm-node-2": {"text": JOURNAL.splitlines()[0]}})
    assert "slurm-node-2's journal (slurmd, munge) says nothing of munge since the job was submitted." in quiet
    assert "Fix: see journalctl -u slurmd -u munge and scontrol show node on slurm-node-2" in quiet
    unread = slurm.stuck_message(
        stuck(), {"slurm-node-2": {"error": "No journal files were opened due to insufficient permissions."}}
    )
    assert (
        "slurm-node-2's journal could not be read: No journal files were opened due to insufficient permissions."
        in unread
    )
    elsewhere = slurm.stuck_message(stuck(), {})
    assert "slurm-node-2 is not a host of the inventory: its journal was not read." in elsewhere


def test_progress_names_the_nodes_slurmctld_gets_no_answer_from():
    job = dict(slurm.parse_scontrol_job(SCONTROL_COMPLETING), not_responding=["slurm-node-2"])
    assert slurm.progress_line(job) == "job 3 COMPLETING 00:00:00 slurm-node-2 - not responding: slurm-node-2"


def test_a_requeued_job_is_what_its_last_end_in_the_completion_log_says():
    # `sacct -c` on the cluster scenario after a node refused a job's launch (munge) and the job ran
    # again once the node's key was the controller's
    log = "4|NODE_FAIL|0:0|00:00:00|slurm-node-2\n4|COMPLETED|0:0|00:00:05|slurm-node-2\n"
    assert slurm.parse_sacct(log, "4")["state"] == "COMPLETED"
    assert slurm.status_of("4", "", log)["finished"]
