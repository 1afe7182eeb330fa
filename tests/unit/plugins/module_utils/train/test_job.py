"""job.LoginNode on a login node made of a function: each Slurm command answers what Slurm 22.05
printed (test_slurm's recordings, and the errors scontrol and sacct print for a job they do not
know and on a cluster without an accounting database); files go to a real directory. What it runs,
in which order, what it writes, and what it fails with."""

from __future__ import annotations

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.train import job, slurm
from ansible_collections.isaacsim.fleet.tests.unit.plugins.module_utils.train.test_slurm import (
    NODE_COMPLETING,
    SCONTROL_COMPLETING,
    SCONTROL_PENDING,
    SCONTROL_RUNNING,
    SINFO,
)

INVALID_JOB = (1, "", "slurm_load_jobs error: Invalid job id specified\n")
NO_ACCOUNTING = (1, "", "Slurm accounting storage is disabled\n")
SACCT_FIELDS = ["-n", "-P", "-o", slurm.SACCT_FIELDS, "-j"]


class Scripted:
    """run(argv) for LoginNode: the answer of the longest of `answers`' word tuples that starts
    argv, (0, "", "") for none; every argv is kept in ran."""

    def __init__(self, answers=None):
        self.answers = dict(answers or {})
        self.answers.setdefault(("sinfo",), (0, SINFO, ""))
        self.ran = []

    def run(self, argv):
        self.ran.append(list(argv))
        known = [words for words in self.answers if tuple(argv[: len(words)]) == words]
        return self.answers[max(known, key=len)] if known else (0, "", "")

    def commands(self):
        return [" ".join(argv[:2]) for argv in self.ran]


def request(tmp_path, **over) -> dict:
    """A podman job as slurm.complete gives it, its image archive on the (tmp_path) shared path."""
    image = tmp_path / "images" / "lab.tar"
    image.parent.mkdir(exist_ok=True)
    image.write_text("archive")
    given = {"name": "train-ant", "time": "10", "nodes": 1, "gpus_per_node": 1, "runtime": "podman"}
    given.update(image_file=str(image), image_id="sha256:0a45aa", script="scripts/train.py")
    given.update(code_dir=f"{tmp_path}/code/", log_dir=str(tmp_path / "slurm-logs"), cache_dir=str(tmp_path / "cache"))
    given.update(over)
    return slurm.complete(given)


def test_submit_writes_the_scripts_then_snapshots_the_code_with_rsync_then_calls_sbatch(tmp_path):
    login = Scripted({("sbatch",): (0, "4711\n", "")})
    result = job.LoginNode(login.run).submit(request(tmp_path), str(tmp_path / "jobs"))
    assert result["changed"] and result["job_id"] == "4711"
    where = tmp_path / "jobs" / result["scripts"]["batch"].split("/")[-2]
    assert where.name.startswith("train-ant-") and result["scripts"] == {
        "batch": f"{where}/batch.sh",
        "node": f"{where}/node.sh",
    }
    assert login.ran == [
        ["sinfo", "-h", "-e", "-o", slurm.SINFO_FORMAT],
        ["rsync", "-a", "--exclude=/logs/", f"--link-dest={tmp_path}/code", f"{tmp_path}/code/", f"{where}/code/"],
        ["sbatch", "--parsable", f"--chdir={where}/code", f"{where}/batch.sh"],
    ]
    # the diff shows each script as written, node script first
    paths = [shown["after_header"] for shown in result["diff"]]
    assert paths == [f"{where}/node.sh", f"{where}/batch.sh"]
    for shown in result["diff"]:
        assert (shown["before"], shown["before_header"]) == ("", shown["after_header"])
        assert (where / shown["after_header"].split("/")[-1]).read_text() == shown["after"]
    assert (where / "node.sh").stat().st_mode & 0o777 == 0o755
    assert (where / "batch.sh").read_text().endswith(f" bash {where}/node.sh\n")
    assert f"--volume={tmp_path}/code/logs:/workspace/isaaclab/logs:rw" in (where / "node.sh").read_text()
    for made in (tmp_path / "code" / "logs", tmp_path / "slurm-logs", where / "code" / "logs"):
        assert made.is_dir()


def test_check_mode_shows_the_scripts_writes_nothing_and_runs_only_sinfo(tmp_path):
    login = Scripted()
    # the image is copied to the cluster after the check: only named in check mode
    given = request(tmp_path, image_file=str(tmp_path / "images" / "not-copied-yet.tar"))
    result = job.LoginNode(login.run, check=True).submit(given, str(tmp_path / "jobs"))
    assert result["changed"] and result["job_id"] is None
    assert [shown["after_header"] for shown in result["diff"]] == [
        result["scripts"]["node"],
        result["scripts"]["batch"],
    ]
    assert "podman load -q -i" in result["diff"][0]["after"]
    assert login.commands() == ["sinfo -h"]
    assert sorted(path.name for path in tmp_path.iterdir()) == ["images"]


@pytest.mark.parametrize(
    ("over", "variable"),
    [
        ({"gpus_per_node": 3}, "train_gpus_per_node: 3, and no node of partition gpu has more than 2."),
        ({"time": "abc"}, "train_time: 'abc' does not parse as a Slurm time."),
        ({"runtime": "singularity"}, "train_runtime: 'singularity'. Fix: one of apptainer,"),
        ({"image_file": "/nowhere/lab.tar"}, "train_image: the job's image is not on the cluster (/nowhere/lab.tar)."),
    ],
)
def test_a_request_error_names_the_variable_and_nothing_is_written_or_submitted(tmp_path, over, variable):
    login = Scripted()
    with pytest.raises(job.JobError) as refused:
        job.LoginNode(login.run).submit(request(tmp_path, **over), str(tmp_path / "jobs"))
    assert refused.value.result["errors"] == [str(refused.value)]
    assert str(refused.value).startswith(variable) and "Fix: " in str(refused.value)
    assert login.commands() == ["sinfo -h"] and not (tmp_path / "jobs").exists()


def test_the_check_reports_every_error_at_once_and_a_good_request_changes_nothing(tmp_path):
    node = job.LoginNode(Scripted().run)
    with pytest.raises(job.JobError) as refused:
        node.act({"state": "checked", "job": {"name": "x", "time": "abc", "gpus_per_node": 3, "runtime": ""}})
    named = [error.split(":")[0] for error in refused.value.result["errors"]]
    assert named == ["train_time", "train_gpus_per_node", "train_runtime"]
    assert str(refused.value) == " ".join(refused.value.result["errors"])
    assert node.act({"state": "checked", "job": request(tmp_path)}) == {"changed": False}


def test_a_failed_command_is_an_error_with_its_words_and_exit_status(tmp_path):
    login = Scripted({("sinfo",): (1, "", "sinfo: error: Unable to contact slurm controller (connect failure)\n")})
    with pytest.raises(job.JobError) as failed:
        job.LoginNode(login.run).submit(request(tmp_path), str(tmp_path / "jobs"))
    assert str(failed.value) == (
        f"sinfo -h -e -o {slurm.SINFO_FORMAT} failed (1): sinfo: error: Unable to contact slurm controller "
        "(connect failure)"
    )
    assert failed.value.result == {"rc": 1}
    # sbatch that answers without a job id
    login = Scripted({("sbatch",): (0, "sbatch: error: Batch job submission failed\n", "")})
    with pytest.raises(job.JobError, match="^sbatch printed no job id: sbatch: error") as failed:
        job.LoginNode(login.run).submit(request(tmp_path), str(tmp_path / "jobs"))
    assert failed.value.result == {}


def test_a_job_slurmctld_has_forgotten_is_read_from_accounting_then_from_the_job_completion_log():
    ended = (0, "17|FAILED|3:0|00:00:12|node-1\n17.batch|FAILED|3:0|00:00:12|node-1\n", "")
    # a cluster with an accounting database
    login = Scripted({("scontrol",): INVALID_JOB, ("sacct", "-X"): ended})
    status = job.LoginNode(login.run).query("17")
    assert (status["state"], status["exit_code"], status["finished"]) == ("FAILED", 3, True)
    assert login.ran == [["scontrol", "show", "job", "-o", "17"], ["sacct", "-X"] + SACCT_FIELDS + ["17"]]
    # one without: the job completion log
    login = Scripted({("scontrol",): INVALID_JOB, ("sacct", "-X"): NO_ACCOUNTING, ("sacct", "-c"): ended})
    assert job.LoginNode(login.run).query("17")["state"] == "FAILED"
    assert login.ran[1:] == [["sacct", "-X"] + SACCT_FIELDS + ["17"], ["sacct", "-c"] + SACCT_FIELDS + ["17"]]
    # accounting that answers without this job
    login = Scripted({("scontrol",): INVALID_JOB, ("sacct", "-X"): (0, "", ""), ("sacct", "-c"): ended})
    assert job.LoginNode(login.run).query("17")["finished"]
    assert login.commands() == ["scontrol show", "sacct -X", "sacct -c"]


def test_an_unknown_job_id_is_an_error_that_says_the_fix():
    login = Scripted({("scontrol",): INVALID_JOB, ("sacct", "-X"): NO_ACCOUNTING})
    with pytest.raises(job.JobError) as unknown:
        job.LoginNode(login.run).act({"state": "query", "job_id": "99"})
    assert str(unknown.value) == (
        "train_job_id: Slurm knows no job 99 (neither slurmctld nor accounting nor the job completion log). "
        "Fix: the id sbatch printed."
    )
    assert unknown.value.result == {}


def test_a_running_or_completing_job_is_read_with_its_nodes_a_pending_one_without():
    login = Scripted(
        {
            ("scontrol", "show", "job"): (0, SCONTROL_COMPLETING, ""),
            ("scontrol", "show", "node"): (0, NODE_COMPLETING, ""),
        }
    )
    status = job.LoginNode(login.run).query("3")
    assert status["state"] == slurm.COMPLETING and not status["finished"]
    assert status["not_responding"] == ["slurm-node-2"]
    assert status["node_states"]["slurm-node-2"]["state"] == "IDLE+COMPLETING+NOT_RESPONDING"
    assert status["submitted_at"] == slurm.epoch("2026-11-24T13:42:32") and "submitted" not in status
    assert login.ran[1] == ["scontrol", "show", "node", "-o", "slurm-node-2"] and len(login.ran) == 2
    # a node read that fails leaves the job's nodes unknown, not the job
    login = Scripted(
        {("scontrol", "show", "job"): (0, SCONTROL_RUNNING, ""), ("scontrol", "show", "node"): INVALID_JOB}
    )
    assert job.LoginNode(login.run).query("17")["node_states"] == {}
    login = Scripted({("scontrol",): (0, SCONTROL_PENDING, "")})
    assert "node_states" not in job.LoginNode(login.run).query("18") and len(login.ran) == 1


def test_a_job_is_cancelled_only_while_it_has_not_ended_and_never_in_check_mode():
    running = {("scontrol", "show", "job"): (0, SCONTROL_RUNNING, "")}
    login = Scripted(running)
    cancelled = job.LoginNode(login.run).act({"state": "cancelled", "job_id": "17"})
    assert (cancelled["changed"], cancelled["job_id"], cancelled["state"]) == (True, "17", "RUNNING")
    assert login.ran[-1] == ["scancel", "17"]
    login = Scripted(running)
    assert job.LoginNode(login.run, check=True).act({"state": "cancelled", "job_id": "17"})["changed"]
    assert login.commands() == ["scontrol show", "scontrol show"]
    login = Scripted({("scontrol",): INVALID_JOB, ("sacct", "-X"): (0, "17|CANCELLED by 0|0:15|00:01:00|node-1\n", "")})
    done = job.LoginNode(login.run).act({"state": "cancelled", "job_id": "17"})
    assert (done["changed"], done["state"], done["signal"]) == (False, "CANCELLED", 15)
    assert "scancel" not in " ".join(login.commands())
    # finished and query only look
    login = Scripted(running)
    assert job.LoginNode(login.run).act({"state": "finished", "job_id": "17"})["changed"] is False
    assert login.commands() == ["scontrol show", "scontrol show"]
