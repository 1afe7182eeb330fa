"""The isaac_sim_train_job module against recording stand-ins for Slurm's commands (sinfo,
sbatch, squeue, sacct, scancel on PATH, printing what Slurm 22.05 prints): what it refuses before
submitting, what it writes and submits, where it reads a finished job."""

from __future__ import annotations

import stat

import pytest
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_train_job
from ansible_collections.isaacsim.fleet.tests.unit.helpers import run_module

SINFO = "gpu*|2|2|20009|gpu:2|infinite\ngpu*|1|2|20009|gpu:1|infinite\n"


@pytest.fixture()
def slurm(tmp_path, monkeypatch):
    """Stand-in Slurm commands: each records its words; SACCT_DB=off answers as a cluster without
    an accounting database; SQUEUE, SACCT_C hold what they print."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    scripts = {
        "sinfo": f"printf '{SINFO}'",
        "sbatch": "echo 4711",
        "squeue": 'printf "%s" "$SQUEUE"',
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
    monkeypatch.setenv("SQUEUE", "")
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


def test_a_bad_request_is_refused_with_every_error_and_nothing_is_written_or_submitted(slurm, capsys):
    result = run_module(
        isaac_sim_train_job.main,
        {
            "job": job(slurm, gpus_per_node=3, time="abc", image_file=str(slurm / "none.tar")),
            "job_dir": str(slurm / "jobs"),
        },
        capsys,
    )
    assert result["failed"]
    assert [e.split(":")[0] for e in result["errors"]] == ["train_time", "train_gpus_per_node", "train_image"]
    assert calls(slurm) == ["sinfo"] and not (slurm / "jobs").exists()


def test_check_mode_shows_the_scripts_and_submits_nothing(slurm, capsys):
    args = {"job": job(slurm), "job_dir": str(slurm / "jobs"), "_ansible_check_mode": True, "_ansible_diff": True}
    result = run_module(isaac_sim_train_job.main, args, capsys)
    assert result["changed"] and result["job_id"] is None
    assert "exec srun --kill-on-bad-exit=1" in result["diff"][1]["after"]
    assert calls(slurm) == ["sinfo"] and not (slurm / "jobs").exists()


def test_a_submit_writes_the_scripts_once_and_returns_sbatch_s_id(slurm, capsys):
    args = {"job": job(slurm), "job_dir": str(slurm / "jobs")}
    result = run_module(isaac_sim_train_job.main, args, capsys)
    assert result["changed"] and result["job_id"] == "4711"
    node = (slurm / "jobs").glob("train-ant-*/node.sh")
    text = next(node).read_text()
    # the podman node runs the image by its id, loaded from the shared archive
    assert f"podman image inspect 0a45aa >/dev/null 2>&1 || podman load -q -i {slurm}/images/lab.tar" in text
    assert (slurm / "code" / "logs" / "slurm").is_dir()
    again = run_module(isaac_sim_train_job.main, args, capsys)
    assert again["scripts"] == result["scripts"] and again["diff"][0]["before"] == again["diff"][0]["after"]


def test_a_finished_job_is_read_from_the_job_completion_log_without_a_database(slurm, capsys, monkeypatch):
    monkeypatch.setenv("SQUEUE", "4711|RUNNING|1:02|node-1|None\n")
    running = run_module(isaac_sim_train_job.main, {"state": "query", "job_id": "4711"}, capsys)
    assert running["finished"] is False and running["state"] == "RUNNING" and running["nodes"] == "node-1"
    # squeue still lists it as done, the completion record is not written yet: not finished
    monkeypatch.setenv("SQUEUE", "4711|COMPLETED|1:05|node-1|None\n")
    assert run_module(isaac_sim_train_job.main, {"state": "query", "job_id": "4711"}, capsys)["finished"] is False
    monkeypatch.setenv("SQUEUE", "")
    monkeypatch.setenv("SACCT_C", "4711|FAILED|3:0|00:01:05|node-1\n")
    done = run_module(isaac_sim_train_job.main, {"state": "query", "job_id": "4711"}, capsys)
    assert done["finished"] and (done["state"], done["exit_code"], done["signal"]) == ("FAILED", 3, 0)


def test_cancel_cancels_a_running_job_only_and_an_unknown_job_is_an_error(slurm, capsys, monkeypatch):
    monkeypatch.setenv("SQUEUE", "4711|RUNNING|1:02|node-1|None\n")
    assert run_module(isaac_sim_train_job.main, {"state": "cancelled", "job_id": "4711"}, capsys)["changed"]
    assert "scancel" in calls(slurm)
    monkeypatch.setenv("SQUEUE", "")
    monkeypatch.setenv("SACCT_C", "4711|CANCELLED by 0|0:15|00:01:05|node-1\n")
    done = run_module(isaac_sim_train_job.main, {"state": "cancelled", "job_id": "4711"}, capsys)
    assert done["changed"] is False and done["state"] == "CANCELLED"
    monkeypatch.setenv("SACCT_C", "")
    unknown = run_module(isaac_sim_train_job.main, {"state": "query", "job_id": "99"}, capsys)
    assert unknown["failed"] and "Slurm knows no job 99" in unknown["msg"]
