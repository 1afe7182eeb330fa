# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""A training job on a Slurm cluster, as the login node runs it: the request checked against the
cluster's partitions, the job written and submitted, a job read (slurmctld, then accounting, then
the job completion log) and cancelled. The isaac_sim_train_job module's whole call.

The login node is reached through run(argv) -> (rc, stdout, stderr), which the module binds to
its run_command and the unit tests to a scripted one; files (the job's scripts, its snapshot of
the code) are written where the job says. What the scripts say: slurm.py."""

from __future__ import annotations

import os
import secrets
import time

from ansible_collections.isaacsim.fleet.plugins.module_utils.train import slurm

# what the request check names each job key after (playbooks/train.yml's variables)
_IMAGE_VARIABLE = "train_image"


class JobError(Exception):
    """What the module fails with: this message, and result, the keys it returns beside it."""

    def __init__(self, msg: str, **result):
        super().__init__(msg)
        self.result = result


class LoginNode:
    """The cluster's login node: run(argv) -> (rc, out, err) runs Slurm's commands (and rsync);
    check: check mode, where nothing is written, submitted or cancelled."""

    def __init__(self, run, check=False):
        self.run, self.check = run, check

    def _run(self, argv, check_rc=True):
        rc, out, err = self.run(argv)
        if check_rc and rc != 0:
            raise JobError(f"{' '.join(argv)} failed ({rc}): {(err or out).strip()}", rc=rc)
        return rc, out, err

    def request_errors(self, job: dict) -> list:
        """What is wrong with the request, against the partitions sinfo lists."""
        _rc, out, _err = self._run(["sinfo", "-h", "-e", "-o", slurm.SINFO_FORMAT])
        errors = slurm.check_request(job, slurm.parse_sinfo(out))
        if job.get("runtime") not in slurm.RUNTIMES:
            errors.append(f"train_runtime: {job.get('runtime')!r}. Fix: one of {', '.join(slurm.RUNTIMES)}.")
        return errors

    def image_errors(self, job: dict) -> list:
        """The image the nodes read must be on the shared path before anything is submitted (in
        check mode it is not copied, so only named)."""
        path = slurm.image_path(job)
        if not path or not (self.check or os.path.isfile(path)):
            return [
                f"{_IMAGE_VARIABLE}: the job's image is not on the cluster ({path or 'no path'}). "
                "Fix: submit with playbooks/train.yml, which builds and copies it, or copy it there."
            ]
        return []

    def checked(self, job: dict) -> dict:
        """state=checked: the request's errors, all of them, or nothing changed."""
        errors = self.request_errors(job)
        if errors:
            raise JobError(" ".join(errors), errors=errors)
        return {"changed": False}

    def submit(self, job: dict, job_dir: str) -> dict:
        """state=submitted, job as slurm.complete gives it: a snapshot of the code, the batch and
        node scripts in a directory of their own under job_dir, and sbatch."""
        errors = self.request_errors(job) + self.image_errors(job)
        if errors:
            raise JobError(" ".join(errors), errors=errors)
        stamp = time.strftime("%Y%m%d-%H%M%S-") + secrets.token_hex(2)
        where = os.path.join(job_dir, slurm.run_dir(job["name"], stamp))
        synced = job["code_dir"].rstrip("/")
        # the job runs a snapshot of the code; its logs/ is the shared one, which comes back
        run = dict(job, code_dir=os.path.join(where, "code"), logs_dir=os.path.join(synced, "logs"))
        scripts = {"batch": os.path.join(where, "batch.sh"), "node": os.path.join(where, "node.sh")}
        texts = {"node": slurm.node_script(run), "batch": slurm.batch_script(run, scripts["node"])}
        diff = [
            {"before": "", "after": texts[k], "before_header": scripts[k], "after_header": scripts[k]} for k in texts
        ]
        if self.check:
            return {"changed": True, "job_id": None, "scripts": scripts, "diff": diff}
        # Slurm does not make the output's directory
        for path in (run["logs_dir"], job["log_dir"], os.path.join(run["code_dir"], "logs")):
            os.makedirs(path, exist_ok=True)
        # hard links to the synced files: a later sync writes new files and never changes these
        self._run(["rsync", "-a", "--exclude=/logs/", f"--link-dest={synced}", f"{synced}/", f"{run['code_dir']}/"])
        for key, path in scripts.items():
            with open(path, "w", encoding="utf-8") as handle:
                handle.write(texts[key])
            os.chmod(path, 0o755)
        _rc, out, _err = self._run(["sbatch", "--parsable", f"--chdir={run['code_dir']}", scripts["batch"]])
        job_id = slurm.submitted_id(out)
        if not job_id:
            raise JobError(f"sbatch printed no job id: {out.strip()}")
        return {"changed": True, "job_id": job_id, "scripts": scripts, "diff": diff}

    def query(self, job_id: str) -> dict:
        """The job's status (slurm.status_of), with its nodes' states while it runs or completes."""
        rc, live, err = self._run(["scontrol", "show", "job", "-o", job_id], False)
        down = ""
        if slurm.controller_down(rc, err):
            down = ((err or live).strip().splitlines() or [f"scontrol exited {rc}"])[-1]
        done = ""
        if not slurm.parse_scontrol_job(live):
            # slurmctld has forgotten it (MinJobAge): accounting, or the job completion log
            fields = ["-n", "-P", "-o", slurm.SACCT_FIELDS, "-j", job_id]
            rc, done, _err = self._run(["sacct", "-X"] + fields, False)
            if rc != 0 or not slurm.parse_sacct(done, job_id):
                _rc, done, _err = self._run(["sacct", "-c"] + fields, False)
        status = slurm.status_of(job_id, live, done, down)
        if status is None:
            raise JobError(
                f"train_job_id: Slurm knows no job {job_id} (neither slurmctld nor accounting nor the job completion "
                "log). Fix: the id sbatch printed."
            )
        if status["state"] in ("RUNNING", slurm.COMPLETING) and status["nodes"] and not status.get("controller_down"):
            # whether slurmctld hears from the job's nodes (a node that refuses its messages keeps a job COMPLETING)
            rc, text, _err = self._run(["scontrol", "show", "node", "-o", status["nodes"]], False)
            nodes = slurm.parse_nodes(text) if rc == 0 else {}
            status.update(node_states=nodes, not_responding=slurm.not_responding(nodes))
        submitted = status.pop("submitted", "")
        if submitted:
            status["submitted_at"] = slurm.epoch(submitted)
        return status

    def looked(self, job_id: str, cancel=False) -> dict:
        """state=query and state=finished (the action plugin polls query), or with cancel
        state=cancelled: scancel for a job that has not ended."""
        status = self.query(job_id)
        if cancel and not status["finished"]:
            if not self.check:
                self._run(["scancel", job_id])
            return dict({"changed": True, "job_id": job_id}, **status)
        return dict({"changed": False, "job_id": job_id}, **status)

    def act(self, p: dict) -> dict:
        """The module's call: its parameters to its result; a failure raises JobError."""
        if p["state"] == "checked":
            return self.checked(p["job"])
        if p["state"] == "submitted":
            return self.submit(slurm.complete(p["job"]), p["job_dir"])
        return self.looked(p["job_id"], cancel=p["state"] == "cancelled")
