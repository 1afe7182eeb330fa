"""The isaac_sim_train_job module against recording stand-ins for Slurm's commands (sinfo,
sbatch, scontrol, sacct, scancel on PATH, printing what Slurm 22.05 prints) and the real rsync:
what it refuses before submitting, what it writes and submits, where it reads a job."""

from __future__ import annotations

import stat

import pytest
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_train_job
from ansible_collections.isaacsim.fleet.tests.unit.helpers import run_module

SINFO = "gpu*|2|2|20009|gpu:2|infinite\ngpu*|1|2|20009|gpu:1|infinite\n"
RUNNING = "JobId=4711 JobName=train-ant JobState=RUNNING Reason=None ExitCode=0:0 RunTime=00:01:02 NodeList=node-1\n"


@pytest.fixture()
def slurm(tmp_path, monkeypatch):
    """Stand-in Slurm commands: each records its words; sacct answers as a cluster without an
    accounting database; SCONTROL, SCONTROL_NODE and SACCT_C hold what scontrol show job, scontrol
    show node and sacct -c print."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    scripts = {
        "sinfo": f"printf '{SINFO}'",
        "sbatch": "echo 4711",
        "scontrol": (
            'if [ "$2" = node ]; then printf "%s" "$SCONTROL_NODE"; exit 0; fi\n'
            '[ -n "$SCONTROL" ] || { echo "slurm_load_jobs error: Invalid job id specified" >&2; exit 1; }\n'
            'printf "%s" "$SCONTROL"'
        ),
        "sacct": (
            'if [ "$1" = -c ]; then printf "%s" "$SACCT_C"; exit 0; fi\n'
            'echo "Slurm accounting storage is disabled" >&2; exit 1'
        ),
        "scancel": "exit 0",
    }
    for name, body in scripts.items():
        path = bin_dir / name
        path.write_text(f'#!/bin/sh\necho "{name} $*" >> "{tmp_path}/calls"\n{body}\n')
        path.chmod(path.stat().st_mode | stat.S_IEXEC)
    monkeypatch.setenv("PATH", f"{bin_dir}:/usr/bin:/bin")
    monkeypatch.setenv("SCONTROL", "")
    monkeypatch.setenv("SCONTROL_NODE", "")
    monkeypatch.setenv("SACCT_C", "")
    return tmp_path


def calls(tmp_path) -> list:
    path = tmp_path / "calls"
    return [line.split()[0] for line in path.read_text().splitlines()] if path.exists() else []


def job(tmp_path, **over):
    image = tmp_path / "images" / "lab.tar"
    image.parent.mkdir(exist_ok=True)
    image.write_text("archive")
    given = dict(
        name="train-ant",
        partition="",
        nodes=1,
        gpus_per_node=1,
        cpus_per_node=1,
        time="10",
        runtime="podman",
        release="6.x",
        image_file=str(image),
        image_id="sha256:0a45aa",
        code_dir=str(tmp_path / "code"),
        log_dir=str(tmp_path / "code" / "logs" / "slurm"),
        cache_dir=str(tmp_path / "cache"),
        script="scripts/train.py",
        args=["--task=Isaac-Ant-v0"],
    )
    given.update(over)
    return given


def query(job_id, capsys, state="query"):
    return run_module(isaac_sim_train_job.main, {"state": state, "job_id": job_id}, capsys)


def test_a_bad_request_is_refused_with_every_error_and_nothing_is_written_or_submitted(slurm, capsys):
    bad = job(slurm, gpus_per_node=3, time="abc", image_file=str(slurm / "none.tar"), env_names=["A-B"])
    result = run_module(isaac_sim_train_job.main, {"job": bad, "job_dir": str(slurm / "jobs")}, capsys)
    assert result["failed"]
    named = [e.split(":")[0] for e in result["errors"]]
    assert named == ["train_time", "train_gpus_per_node", "train_env", "train_image"]
    assert calls(slurm) == ["sinfo"] and not (slurm / "jobs").exists()


def test_check_mode_shows_the_scripts_and_submits_nothing(slurm, capsys):
    # a first submit in check mode: the image is not on the cluster yet, and that is no error
    given = job(slurm, image_file=str(slurm / "images" / "not-copied-yet.tar"))
    args = {"job": given, "job_dir": str(slurm / "jobs"), "_ansible_check_mode": True, "_ansible_diff": True}
    result = run_module(isaac_sim_train_job.main, args, capsys)
    assert result["changed"] and result["job_id"] is None
    assert "exec srun --kill-on-bad-exit=1" in result["diff"][1]["after"]
    assert calls(slurm) == ["sinfo"] and not (slurm / "jobs").exists()


def test_each_submit_runs_a_snapshot_of_the_code_that_the_next_sync_cannot_change(slurm, capsys):
    code = slurm / "code"
    (code / "scripts").mkdir(parents=True)
    (code / "scripts" / "train.py").write_text("v1")
    (code / "logs" / "old").mkdir(parents=True)
    args = {"job": job(slurm), "job_dir": str(slurm / "jobs")}
    result = run_module(isaac_sim_train_job.main, args, capsys)
    assert result["changed"] and result["job_id"] == "4711"
    run = slurm / "jobs" / result["scripts"]["node"].split("/")[-2]
    text = (run / "node.sh").read_text()
    # the podman node runs the image by its id, loaded from the shared archive
    assert f"podman image inspect 0a45aa >/dev/null 2>&1 || podman load -q -i {slurm}/images/lab.tar" in text
    # the snapshot as the container's code, the shared logs/ over its logs/
    assert f"--volume={run}/code:/workspace/isaaclab:rw" in text
    assert f"--volume={code}/logs:/workspace/isaaclab/logs:rw" in text
    assert (run / "code" / "scripts" / "train.py").stat().st_ino == (code / "scripts" / "train.py").stat().st_ino
    assert not (run / "code" / "logs" / "old").exists() and (code / "logs" / "slurm").is_dir()
    assert f"sbatch --parsable --chdir={run}/code {run}/batch.sh" in (slurm / "calls").read_text()
    # the next sync writes new files (rsync's default): this job's code stays as it was
    (code / "scripts" / "train.py").unlink()
    (code / "scripts" / "train.py").write_text("v2")
    assert (run / "code" / "scripts" / "train.py").read_text() == "v1"
    again = run_module(isaac_sim_train_job.main, args, capsys)
    assert again["scripts"]["node"] != result["scripts"]["node"]


def test_a_job_is_read_from_slurmctld_then_from_the_job_completion_log(slurm, capsys, monkeypatch):
    monkeypatch.setenv("SCONTROL", RUNNING)
    running = query("4711", capsys)
    assert running["finished"] is False and running["state"] == "RUNNING" and running["nodes"] == "node-1"
    assert "sacct" not in calls(slurm)
    # slurmctld has the end and its exit status, wherever the login node is
    monkeypatch.setenv("SCONTROL", RUNNING.replace("JobState=RUNNING", "JobState=FAILED").replace("=0:0", "=3:0"))
    ended = query("4711", capsys)
    assert ended["finished"] and ended["exit_code"] == 3
    # after MinJobAge slurmctld has forgotten it: the job completion log
    monkeypatch.setenv("SCONTROL", "")
    monkeypatch.setenv("SACCT_C", "4711|FAILED|3:0|00:01:05|node-1\n")
    done = query("4711", capsys)
    assert done["finished"] and (done["state"], done["exit_code"], done["signal"]) == ("FAILED", 3, 0)


def test_cancel_cancels_a_running_job_only_and_an_unknown_job_is_an_error(slurm, capsys, monkeypatch):
    monkeypatch.setenv("SCONTROL", RUNNING)
    assert query("4711", capsys, "cancelled")["changed"]
    assert "scancel" in calls(slurm)
    monkeypatch.setenv("SCONTROL", "")
    monkeypatch.setenv("SACCT_C", "4711|CANCELLED by 0|0:15|00:01:05|node-1\n")
    done = query("4711", capsys, "cancelled")
    assert done["changed"] is False and done["state"] == "CANCELLED"
    monkeypatch.setenv("SACCT_C", "")
    unknown = query("99", capsys)
    assert unknown["failed"] and "Slurm knows no job 99" in unknown["msg"]


def test_the_nodes_of_a_running_or_completing_job_are_read_with_their_state(slurm, capsys, monkeypatch):
    # slurm-node-2 refuses slurmctld's messages (its munge key is another): the job stays COMPLETING
    monkeypatch.setenv(
        "SCONTROL",
        RUNNING.replace("RUNNING", "COMPLETING").replace(" RunTime", " SubmitTime=2026-11-24T13:42:32 RunTime"),
    )
    monkeypatch.setenv(
        "SCONTROL_NODE", "NodeName=node-1 Arch=x86_64 State=IDLE+COMPLETING+NOT_RESPONDING ThreadsPerCore=1\n"
    )
    completing = query("4711", capsys)
    assert completing["state"] == "COMPLETING" and not completing["finished"]
    assert completing["node_states"] == {"node-1": {"state": "IDLE+COMPLETING+NOT_RESPONDING", "reason": ""}}
    assert completing["not_responding"] == ["node-1"]
    assert isinstance(completing["submitted_at"], int) and "submitted" not in completing
    assert "scontrol show node -o node-1" in (slurm / "calls").read_text()
    # a pending job has no nodes to read
    monkeypatch.setenv("SCONTROL", "JobId=4711 JobName=train-ant JobState=PENDING Reason=Priority NodeList=(null)\n")
    pending = query("4711", capsys)
    assert "node_states" not in pending and (slurm / "calls").read_text().count("show node") == 1
