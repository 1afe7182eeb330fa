"""Isaac Lab training on the test cluster through playbooks/train.yml, as a team runs it from its
controller: the team's image (a stand-in Isaac Lab image, built here in this machine's Docker) and
its code (a stand-in checkout with a training script that writes logs and checkpoints) go to the
cluster, Slurm runs the job in Podman on a compute node, and the playbook follows it, brings its
logs back and ends with its exit status. In order: bad requests (nothing reaches the cluster), a
first job, a second submit (nothing copied, deletions applied, 2 GPUs, a failing exit), a new image
and a cancel, and a node whose munge key is not the controller's."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import time
from concurrent.futures import ThreadPoolExecutor

import pytest
import testbed
from clusterhosts import CONTROLLER, PLAIN, playbook, playbook_command, sh, squash
from testbed import ROOT, client

FIXTURE = ROOT / "tests" / "fixtures" / "isaac-lab"
IMAGE = "isaacsim-fleet/isaac-lab-standin:cluster-test"
# molecule/cluster/inventory: slurm_login's train_cluster_dir
LAB = "/shared/isaaclab/lab"
IMAGES = f"{LAB}/images"


def image_file(image_id: str) -> str:
    """The job image on the cluster: the team's image name and its id."""
    return f"{IMAGES}/isaacsim-fleet_isaac-lab-standin_cluster-test-{image_id.split(':')[1][:12]}.tar"


NOTE = '--note=it\'s a "test" $HOME'


def build_image(variant: int) -> str:
    """The stand-in image in this machine's Docker (the controller's); a new variant, a new id."""
    subprocess.run(
        ["docker", "build", "-q", "--build-arg", f"VARIANT={variant}", "-t", IMAGE, str(FIXTURE)],
        check=True,
        capture_output=True,
    )
    return client().images.get(IMAGE).id


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    """The team's side: a copy of the stand-in checkout with a file that a later commit deletes."""
    code = tmp_path_factory.mktemp("team") / "IsaacLab"
    shutil.copytree(FIXTURE / "code", code)
    (code / "scripts" / "old_helper.py").write_text("# deleted before the second submit\n")
    (code / ".git").mkdir()
    (code / ".git" / "HEAD").write_text("ref: refs/heads/main\n")
    return {"code": code, "id": build_image(1)}


def asked(lab, extra=None, **over) -> dict:
    given = {"train_code_dir": str(lab["code"]), "train_image": IMAGE, "train_env": ["SLURMD_NODENAME"]}
    given.update(extra or {})
    given.update(over)
    return given


def train(lab, extra=None, **over):
    return playbook("train.yml", asked(lab, extra, **over))


def train_written_as_it_goes(lab, out, **over) -> subprocess.Popen:
    """train() in the background, its output written to the file out as Ansible prints it (unbuffered,
    whatever Ansible's own flushing), for a test that acts on a line of it."""
    cmd = playbook_command("train.yml", asked(lab, **over))
    with out.open("w") as stdout, out.with_suffix(".err").open("w") as stderr:
        return subprocess.Popen(
            cmd, stdout=stdout, stderr=stderr, text=True, env=dict(PLAIN, PYTHONUNBUFFERED="1"), cwd=ROOT
        )


def jobs_known() -> str:
    return sh(CONTROLLER, "squeue -h -t all -o %i; sacct -c -n -P -o JobID")


def submitted_id(result) -> str:
    text = squash(result.stdout)
    return text.split(" submitted;", 1)[0].rsplit("job ", 1)[1]


def outcome(result, task: str) -> str:
    """What Ansible printed for a task of the train role: changed, ok, skipping or fatal."""
    match = re.search(rf"{re.escape(task)}\] \*+\n(\w+)", result.stdout)
    assert match, result.stdout[-3000:]
    return match.group(1)


def rank(job: str, task: str, n: int, code) -> dict:
    return json.loads((code / "logs" / "rsl_rl" / task / f"job-{job}" / f"rank-{n}.json").read_text())


def test_bad_requests_fail_with_every_error_before_anything_reaches_the_cluster(lab):
    before = jobs_known()
    wrong = train(
        lab,
        train_time="abc",
        train_gpus_per_node=3,
        train_image="isaacsim-fleet/no-such-image:1",
        train_script="scripts/missing.py",
        train_nodes=-1,
        train_cpus_per_node=0,
    )
    assert wrong.returncode != 0
    text = squash(wrong.stdout + wrong.stderr)
    for expected in (
        "train_script: scripts/missing.py is not in",
        "train_time: 'abc' does not parse as a Slurm time",
        "train_gpus_per_node: 3, and no node of partition gpu has more than 2",
        "train_image: 'isaacsim-fleet/no-such-image:1' is not an image of the build host's Docker",
        "train_nodes: -1 is not a count of nodes. Fix: a whole number, 1 or more.",
        "train_cpus_per_node: 0 is not a count of CPUs per node",
    ):
        assert expected in text, text[-3000:]
    partition = train(lab, train_partition="cpu")
    assert partition.returncode != 0
    assert "train_partition: 'cpu' is not a partition of the cluster. Fix: one of gpu." in squash(
        partition.stdout + partition.stderr
    )
    # nothing submitted, nothing copied or synced, nothing built
    assert jobs_known() == before
    assert "absent" in sh(CONTROLLER, f"test -e {LAB} || echo absent")


def test_a_training_job_outlives_a_slurmctld_outage_writes_logs_and_checkpoints_and_its_logs_come_back(lab, tmp_path):
    args = ["--task=Isaac-Ant-v0", "--max_iterations=3", NOTE, "--headless", "--sleep=5"]
    out = tmp_path / "train.out"
    running = train_written_as_it_goes(lab, out, train_cpus_per_node=2, train_poll_interval=3, train_args=args)
    try:
        # once the training runs (its srun step, which slurmctld must create, exists), slurmctld goes
        # away until the playbook has said it does not answer and the job has ended meanwhile (its caches
        # copied back to the shared ones: the node script's last step), or for 45 s at most, as it did
        # before (the first job loads its image on the node); the job's end waits on slurmd. Stopped
        # earlier, the job script's srun (and its scontrol) would fail on the missing controller: Slurm's
        # behaviour
        step = testbed.wait_for(
            lambda: re.search(r"^(\d+)\.0$", sh(CONTROLLER, "squeue -h -s -o %i"), re.M),
            timeout=120,
            interval=0.5,
            what="the training's srun step",
        )
        stepped = step.group(1)
        shared = f"cat {LAB}/cache/cache/main/standin-shaders 2>/dev/null; true"
        sh(CONTROLLER, "systemctl stop slurmctld")
        stopped = time.monotonic()
        try:
            testbed.wait_for(
                lambda: "slurmctld does not answer" in out.read_text()
                and (time.monotonic() - stopped >= 45 or stepped in sh(CONTROLLER, shared).split()),
                timeout=60,
                what=f"the playbook to find slurmctld away (and job {stepped} to end)",
            )
        finally:
            sh(CONTROLLER, "systemctl start slurmctld")
        running.wait(timeout=600)
    finally:
        if running.poll() is None:
            running.kill()
            running.wait()
    done = subprocess.CompletedProcess(
        running.args, running.returncode, out.read_text(), out.with_suffix(".err").read_text()
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr
    text = squash(done.stdout)
    job = submitted_id(done)
    assert "slurmctld does not answer (slurm_load_jobs error: Unable to contact slurm controller" in text, text[-3000:]
    assert "waiting for it" in text
    # followed: a line per change of state, then the end
    assert f"slurm-ctl: job {job} COMPLETED" in text and f"job {job} COMPLETED on slurm-node-" in text
    run = lab["code"] / "logs" / "rsl_rl" / "Isaac-Ant-v0" / f"job-{job}"
    assert (run / "train.log").read_text().count("iteration") == 3
    assert (run / "model_2.pt").read_bytes() == b"stand-in checkpoint 2\n"
    assert "training on node 0 exited with 0" in (lab["code"] / "logs" / "slurm" / f"slurm-{job}.out").read_text()
    # the checkpoint stays on the cluster too
    sh(CONTROLLER, f"test -s {LAB}/code/logs/rsl_rl/Isaac-Ant-v0/job-{job}/model_2.pt")
    given = rank(job, "Isaac-Ant-v0", 0, lab["code"])
    # every word as written (nothing expanded on the cluster), in Isaac Lab's directory, one GPU
    assert given["argv"] == args
    assert given["cwd"] == "/workspace/isaaclab" and len(given["gpus"]) == 1
    # the CPUs asked for reach the training (srun is told them; Slurm pins the task to them)
    assert given["cpus"] == 2
    assert given["env"]["SLURM_JOB_ID"] == job and "WORLD_SIZE" not in given["env"]
    assert sh(CONTROLLER, f"sacct -c -n -P -o State,ExitCode -j {job}").strip() == "COMPLETED|0:0"
    # the image was built and copied once, with the id it came from beside it
    assert outcome(done, "Copy the job image to the cluster") == "changed"
    assert sh(CONTROLLER, f"ls {IMAGES}").split() == [image_file(lab["id"]).rsplit("/", 1)[1]]
    assert sh(CONTROLLER, f"stat -c %a {image_file(lab['id'])}").strip() == "644"
    # the node-local cache came back to the shared one
    assert job in sh(CONTROLLER, f"cat {LAB}/cache/cache/main/standin-shaders").split()
    # .git never goes to the cluster
    assert "absent" in sh(CONTROLLER, f"test -e {LAB}/code/.git || echo absent")


def test_a_second_submit_copies_nothing_applies_deletions_and_a_failing_2_gpu_job_ends_the_play_with_its_status(lab):
    image_before = sh(CONTROLLER, f"stat -c '%i %Y' {image_file(lab['id'])}")
    first_logs = sh(CONTROLLER, f"ls {LAB}/code/logs/rsl_rl/Isaac-Ant-v0")
    (lab["code"] / "scripts" / "old_helper.py").unlink()
    done = train(lab, train_gpus_per_node=2, train_args=["--task=Isaac-Humanoid-v0", "--exit-code=3"])
    assert done.returncode == 2, done.stdout[-3000:]
    job = submitted_id(done)
    text = squash(done.stdout + done.stderr)
    assert f"job {job} FAILED on slurm-node-1 after" in text and "exit status 3" in text
    # the image did not change: nothing built or copied
    assert sh(CONTROLLER, f"stat -c '%i %Y' {image_file(lab['id'])}") == image_before
    assert outcome(done, "Copy the job image to the cluster") == "skipping"
    # the deleted file is gone on the cluster; earlier jobs' logs stay there
    assert "absent" in sh(CONTROLLER, f"test -e {LAB}/code/scripts/old_helper.py || echo absent")
    assert sh(CONTROLLER, f"ls {LAB}/code/logs/rsl_rl/Isaac-Ant-v0") == first_logs
    # 2 GPUs: only slurm-node-1 has them; torchrun started one process per GPU
    ranks = [rank(job, "Isaac-Humanoid-v0", n, lab["code"]) for n in range(2)]
    assert {r["env"]["SLURMD_NODENAME"] for r in ranks} == {"slurm-node-1"}
    assert [r["env"]["LOCAL_RANK"] for r in ranks] == ["0", "1"] and ranks[0]["env"]["WORLD_SIZE"] == "2"
    assert ranks[0]["gpus"] == ["/dev/nvidia0", "/dev/nvidia1"]
    assert sh(CONTROLLER, f"sacct -c -n -P -o State,ExitCode -j {job}").strip() == "FAILED|3:0"


def test_a_two_node_job_runs_a_task_on_each_node_that_meet_at_the_first_node(lab):
    done = train(lab, train_nodes=2, train_gpus_per_node=1, train_args=["--task=Isaac-Ant-v0"])
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr
    job = submitted_id(done)
    ranks = [rank(job, "Isaac-Ant-v0", n, lab["code"]) for n in range(2)]
    # one process per node under torchrun, each with its node's number, one world of two
    assert sorted(r["env"]["SLURMD_NODENAME"] for r in ranks) == ["slurm-node-1", "slurm-node-2"]
    assert sorted(r["env"]["SLURM_NODEID"] for r in ranks) == ["0", "1"]
    assert {r["env"]["WORLD_SIZE"] for r in ranks} == {"2"}
    # the rendezvous: the first node's address from slurm.conf (NodeAddr), a port of this job
    first = client().containers.get("slurm-node-1").attrs["NetworkSettings"]["IPAddress"]
    assert {(r["env"]["MASTER_ADDR"], r["env"]["MASTER_PORT"]) for r in ranks} == {
        (first, str(29500 + int(job) % 1000))
    }
    assert all(len(r["gpus"]) == 1 for r in ranks)


def test_a_new_image_is_copied_once_and_cancel_ends_a_running_job(lab):
    new_id = build_image(2)
    assert new_id != lab["id"]
    submitted = train(lab, train_wait=False, train_args=["--task=Isaac-Ant-v0", "--sleep=600"])
    assert submitted.returncode == 0, submitted.stdout[-3000:] + submitted.stderr
    job = submitted_id(submitted)
    assert outcome(submitted, "Copy the job image to the cluster") == "changed"
    # a file of its own: the one a queued job may still need is kept beside it
    assert sorted(sh(CONTROLLER, f"ls {IMAGES}").split()) == sorted(
        image_file(i).rsplit("/", 1)[1] for i in (lab["id"], new_id)
    )
    deadline = time.monotonic() + 60
    while "RUNNING" not in sh(CONTROLLER, f"squeue -h -j {job} -o %T", check=False):
        assert time.monotonic() < deadline, sh(CONTROLLER, f"squeue -h -j {job}", check=False)
        time.sleep(1)
    node = sh(CONTROLLER, f"squeue -h -j {job} -o %N").strip()
    deadline = time.monotonic() + 60
    # the job's container runs the new image, loaded by its id
    while f"train-{job}-0" not in sh(node, "podman ps --format '{{.Names}} {{.ImageID}}'"):
        assert time.monotonic() < deadline
        time.sleep(1)
    assert new_id.split(":")[1][:12] in sh(node, "podman ps --format '{{.Names}} {{.ImageID}}'")
    # the caches run from the node's own disk, a directory for this job (slurm_node's local cache);
    # the training has written its checkpoints and then its cache before it is cancelled
    local = f"/var/tmp/isaac-sim-cache/isaac-sim-cache-{job}"
    deadline = time.monotonic() + 60
    while "standin-shaders" not in sh(node, f"ls {local}/cache/main", check=False):
        assert time.monotonic() < deadline
        time.sleep(1)
    sh(CONTROLLER, f"test -s {LAB}/code/logs/rsl_rl/Isaac-Ant-v0/job-{job}/model_2.pt")
    cancelled = train(lab, train_job_id=job, train_cancel=True)
    assert cancelled.returncode == 0, cancelled.stdout[-3000:]
    assert f"job {job} CANCELLED" in squash(cancelled.stdout)
    # Slurm says CANCELLED at once; the node script then stops the container, copies the caches
    # back and removes the job's directory
    deadline = time.monotonic() + 60
    while "absent" not in sh(node, f"test -e {local} || echo absent") or f"train-{job}-" in sh(
        node, "podman ps -a --format '{{.Names}}'"
    ):
        assert time.monotonic() < deadline, sh(node, "podman ps -a; ls /var/tmp/isaac-sim-cache")
        time.sleep(1)
    # what the training wrote to its cache came back to the shared one
    assert job in sh(CONTROLLER, f"cat {LAB}/cache/cache/main/standin-shaders").split()
    assert sh(CONTROLLER, f"sacct -c -n -P -o State -j {job}").strip() == "CANCELLED"


def test_a_node_whose_munge_key_is_not_the_controller_s_is_named_and_cluster_yml_replaces_its_key(lab):
    """A job runs on slurm-node-2, which then gets a munge key of its own: at the job's time limit
    slurmctld ends it, the node refuses the message, and the job stays COMPLETING (Reason=TimeLimit,
    nothing of the node; measured: until slurmctld sets the node DOWN, minutes later). The follow fails after
    train_completing_timeout naming the node and the error in its journal; cluster.yml says it
    replaced that node's key, the stuck job then ends, and a job there completes."""
    key = "/etc/munge/munge.key"
    pinned = {"train_sbatch_options": ["--nodelist=slurm-node-2"], "train_args": ["--task=Isaac-Ant-v0"]}
    try:
        with ThreadPoolExecutor(1) as pool:
            started = time.monotonic()
            # one minute: past it slurmctld ends the job, and asks the node to end it
            running = pool.submit(
                train,
                lab,
                pinned,
                train_time="1",
                train_completing_timeout=15,
                # whatever happens, the follow ends
                train_wait_timeout=400,
                train_args=["--task=Isaac-Ant-v0", "--sleep=600"],
            )
            deadline = time.monotonic() + 120
            while not sh(CONTROLLER, "squeue -h -w slurm-node-2 -t RUNNING -o %i", check=False).strip():
                assert time.monotonic() < deadline, sh(CONTROLLER, "squeue -h -t all", check=False)
                time.sleep(0.5)
            sh(
                "slurm-node-2",
                f"head -c 1024 /dev/urandom > {key} && chown munge:munge {key} && chmod 0400 {key} "
                "&& systemctl restart munge",
            )
            stuck = running.result()
        took = time.monotonic() - started
        assert stuck.returncode == 2, stuck.stdout[-3000:] + stuck.stderr
        job = submitted_id(stuck)
        text = squash(stuck.stdout + stuck.stderr)
        # Slurm's reason is the time limit, not the node; the follow names the node, its state and
        # what its journal says
        assert "JobState=COMPLETING Reason=TimeLimit" in sh(CONTROLLER, f"scontrol show job -o {job}")
        named = re.search(
            rf"job {job} has been COMPLETING for (\d+) s \(Slurm's reason: TimeLimit\): slurmctld waits for "
            r"slurm-node-2 \([A-Z_+]+\) to end it",
            text,
        )
        assert named and int(named.group(1)) >= 15, text[-3000:]
        assert re.search(
            r"slurm-node-2's journal \(slurmd, munge\): \S+ slurm-node-2 slurmd\[\d+\]: "
            r"slurmd-slurm-node-2: error: Munge decode failed: Invalid credential",
            text,
        ), text[-3000:]
        assert "Fix: munge refuses credentials between slurm-node-2 and the controller" in text
        assert f"follow it with train_job_id={job}" in text
        # bounded: the play does not wait for the job
        assert took < 300, took
    finally:
        fixed = playbook("cluster.yml")
    assert fixed.returncode == 0, fixed.stdout[-3000:] + fixed.stderr
    # Ansible's YAML output doubles a quote inside a quoted message
    said = squash(fixed.stdout).replace("''", "'")
    assert "slurm-node-2: its munge key differed from the controller's (slurm-ctl)" in said, said[-3000:]
    assert "replaced with the cluster's key, munge and slurmd restarted" in said
    assert "slurm-node-1: its munge key differed" not in said
    keys = {host: sh(host, f"sha256sum {key}").split()[0] for host in (CONTROLLER, "slurm-node-1", "slurm-node-2")}
    assert len(set(keys.values())) == 1, keys
    # the node answers again: the stuck job ends, and a job there completes
    done = train(lab, pinned)
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr
    assert f"job {submitted_id(done)} COMPLETED on slurm-node-2" in squash(done.stdout)
    assert sh(CONTROLLER, f"sacct -c -n -P -o State -j {job}").split() == ["TIMEOUT"]
