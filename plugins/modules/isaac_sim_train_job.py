#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_train_job
short_description: Submit, follow and cancel an Isaac Lab training job on a Slurm cluster
version_added: "0.4.0"
description:
  - Runs on the cluster's login node, with Slurm's own commands (C(sinfo), C(sbatch), C(scontrol), C(sacct),
    C(scancel)).
  - O(state=checked) checks the request against the cluster's partitions and fails with every error, each naming
    the playbook variable and the fix; nothing changes.
  - O(state=submitted) checks the same way, takes a snapshot of the code for this job (hard links, so the next
    sync never changes the code of a job that waits or runs), writes the batch script and the script each node
    runs (one task per node; the node-local cache copied in and back; the training in the job's container
    runtime, with C(torchrun) past one GPU) and submits it with C(sbatch). Check mode shows the scripts and
    submits nothing.
  - O(state=finished) follows the job until it ends, printing a line (state, elapsed time, nodes) whenever it
    changes, and returns its end (the action plugin polls this module with O(state=query)).
  - O(state=cancelled) cancels it with C(scancel) and waits until Slurm has ended it.
  - A job is read with C(scontrol show job) while slurmctld knows it (until C(MinJobAge) after its end), then with
    C(sacct), from the accounting database, or with C(sacct -c) from the job completion log where the cluster keeps
    no database (that log is on the controller).
author: isaacsim.fleet contributors (@isaacsim-fleet)
options:
  state:
    description: What to do.
    type: str
    default: submitted
    choices: [checked, submitted, query, finished, cancelled]
  job:
    description:
      - The job (O(state=checked) and O(state=submitted)).
      - C(name), C(partition), C(account), C(nodes), C(gpus_per_node), C(cpus_per_node), C(memory), C(time),
        C(modules) (site modules loaded first), C(sbatch_options) (more C(#SBATCH) lines).
      - C(runtime) (apptainer, podman, docker or enroot), C(image_file) (the job image on the cluster, the SIF or
        squashfs file, or the archive podman and docker nodes load), C(image_id) (the team's image id, by which
        podman and docker nodes run it).
      - C(code_dir) (the synced code on the shared file system; each job runs a snapshot of it as the container's
        C(/workspace/isaaclab), with its C(logs/) shared), C(log_dir) (where Slurm writes the job's output),
        C(cache_dir) (the shared Isaac Sim caches), C(local_cache) (the node's directory for the job's copy),
        C(release) (the Isaac Sim release whose cache paths are mounted), or C(mounts) (cache subdirectory to path
        in the container).
      - C(python), C(script), C(args) (as the guide passes them to the Python executable), C(env_names)
        (variables passed into the container).
    type: dict
  job_dir:
    description: Where each submission's scripts and code snapshot are kept, on the shared file system (every node
      reads them).
    type: path
  job_id:
    description: The job (O(state=query), O(state=finished), O(state=cancelled)).
    type: str
  wait_timeout:
    description: Seconds to follow a job before giving up (the job goes on); 0 follows it to its end.
    type: int
    default: 0
  poll_interval:
    description: Seconds between two looks at a job that is followed.
    type: int
    default: 10
  outage_timeout:
    description:
      - Seconds a followed job waits for slurmctld when it does not answer (a restart, a failover); the job is
        never called lost while slurmctld is away, only when slurmctld, accounting and the job completion log all
        no longer know it.
    type: int
    default: 600
  completing_timeout:
    description:
      - Seconds a followed job may stay C(COMPLETING) (slurmctld has ended it and waits for its nodes to say its end
        is done) before the follow fails, naming the nodes it waits for with their state in Slurm; 1 or more.
      - A node whose munge key is not the controller's refuses slurmctld's messages; a job there stays
        C(COMPLETING), and Slurm's reason says nothing of the node. The failed result has RV(stuck_nodes) (the role
        isaacsim.fleet.train then reads their journal); the job is not cancelled.
    type: int
    default: 300
notes:
  - The node script's container command is written for each runtime's documented command line; only the Podman
    path runs in this collection's test cluster (Apptainer is not packaged for its Debian test hosts).
"""

EXAMPLES = r"""
- name: Submit the training
  isaacsim.fleet.isaac_sim_train_job:
    job: "{{ train_job }}"
    job_dir: /shared/isaaclab/jobs
  register: submitted

- name: Follow it to its end
  isaacsim.fleet.isaac_sim_train_job:
    state: finished
    job_id: "{{ submitted.job_id }}"
"""

RETURN = r"""
job_id:
  description: The job's id.
  returned: success, unless O(state=checked)
  type: str
  sample: "4711"
state:
  description: Slurm's state of the job.
  returned: O(state=query), O(state=finished), O(state=cancelled)
  type: str
  sample: COMPLETED
finished:
  description: Whether the job has ended.
  returned: O(state=query), O(state=finished), O(state=cancelled)
  type: bool
exit_code:
  description: The job's exit status (the training's), once it has ended.
  returned: O(state=query), O(state=finished), O(state=cancelled)
  type: int
  sample: 0
signal:
  description: The signal that ended it, 0 for none.
  returned: O(state=query), O(state=finished), O(state=cancelled)
  type: int
elapsed:
  description: Time it ran.
  returned: O(state=query), O(state=finished), O(state=cancelled)
  type: str
  sample: "00:12:31"
nodes:
  description: The nodes it ran on.
  returned: O(state=query), O(state=finished), O(state=cancelled)
  type: str
  sample: gpu-node-[1-2]
node_states:
  description: Slurm's state and reason of each of the job's nodes (C(scontrol show node)), while it runs or completes.
  returned: O(state=query), O(state=finished), O(state=cancelled), when the job is C(RUNNING) or C(COMPLETING)
  type: dict
  sample: {"gpu-node-2": {"state": "IDLE+COMPLETING+NOT_RESPONDING", "reason": ""}}
not_responding:
  description: Those of the job's nodes slurmctld gets no answer from.
  returned: O(state=query), O(state=finished), O(state=cancelled), when the job is C(RUNNING) or C(COMPLETING)
  type: list
  elements: str
  sample: [gpu-node-2]
submitted_at:
  description: When the job was submitted, in seconds since the epoch (from C(SubmitTime), read on the login node).
  returned: O(state=query), O(state=finished), O(state=cancelled), while slurmctld knows the job
  type: int
  sample: 1795354574
stuck_nodes:
  description: The nodes a job that stayed C(COMPLETING) past O(completing_timeout) waits for.
  returned: failure of O(state=finished) or O(state=cancelled) on a job stuck in C(COMPLETING)
  type: list
  elements: str
  sample: [gpu-node-2]
stuck_for:
  description: Seconds the follow saw the job C(COMPLETING).
  returned: failure of O(state=finished) or O(state=cancelled) on a job stuck in C(COMPLETING)
  type: int
  sample: 300
progress:
  description: The lines shown while it was followed.
  returned: O(state=finished), O(state=cancelled)
  type: list
  elements: str
scripts:
  description: The batch script and the node script written for it.
  returned: O(state=submitted)
  type: dict
  sample: {"batch": "/shared/lab/jobs/train-ant-20261124-101500-5f0c/batch.sh",
           "node": "/shared/lab/jobs/train-ant-20261124-101500-5f0c/node.sh"}
errors:
  description: What is wrong with the request, each naming the variable and the fix.
  returned: failure of O(state=checked) or O(state=submitted)
  type: list
  elements: str
"""

import os
import secrets
import time

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.train import slurm

# what the request check names each job key after (playbooks/train.yml's variables)
_IMAGE_VARIABLE = "train_image"


def _run(module, argv, check_rc=True):
    rc, out, err = module.run_command(argv)
    if check_rc and rc != 0:
        module.fail_json(msg=f"{' '.join(argv)} failed ({rc}): {(err or out).strip()}", rc=rc)
    return rc, out, err


def request_errors(module, job):
    _rc, out, _err = _run(module, ["sinfo", "-h", "-e", "-o", slurm.SINFO_FORMAT])
    errors = slurm.check_request(job, slurm.parse_sinfo(out))
    if job.get("runtime") not in slurm.RUNTIMES:
        errors.append(f"train_runtime: {job.get('runtime')!r}. Fix: one of {', '.join(slurm.RUNTIMES)}.")
    return errors


def image_errors(module, job):
    """The image the nodes read must be on the shared path before anything is submitted (in check
    mode it is not copied, so only named)."""
    path = slurm.image_path(job)
    if not path or not (module.check_mode or os.path.isfile(path)):
        return [
            f"{_IMAGE_VARIABLE}: the job's image is not on the cluster ({path or 'no path'}). "
            "Fix: submit with playbooks/train.yml, which builds and copies it, or copy it there."
        ]
    return []


def submit(module, job, job_dir):
    errors = request_errors(module, job) + image_errors(module, job)
    if errors:
        module.fail_json(msg=" ".join(errors), errors=errors)
    where = os.path.join(job_dir, slurm.run_dir(job["name"], time.strftime("%Y%m%d-%H%M%S-") + secrets.token_hex(2)))
    synced = job["code_dir"].rstrip("/")
    # the job runs a snapshot of the code; its logs/ is the shared one, which comes back
    run = dict(job, code_dir=os.path.join(where, "code"), logs_dir=os.path.join(synced, "logs"))
    scripts = {"batch": os.path.join(where, "batch.sh"), "node": os.path.join(where, "node.sh")}
    texts = {"node": slurm.node_script(run), "batch": slurm.batch_script(run, scripts["node"])}
    diff = [{"before": "", "after": texts[k], "before_header": scripts[k], "after_header": scripts[k]} for k in texts]
    if module.check_mode:
        module.exit_json(changed=True, job_id=None, scripts=scripts, diff=diff)
    # Slurm does not make the output's directory
    for path in (run["logs_dir"], job["log_dir"], os.path.join(run["code_dir"], "logs")):
        os.makedirs(path, exist_ok=True)
    # hard links to the synced files: a later sync writes new files and never changes these
    _run(module, ["rsync", "-a", "--exclude=/logs/", f"--link-dest={synced}", f"{synced}/", f"{run['code_dir']}/"])
    for key, path in scripts.items():
        with open(path, "w", encoding="utf-8") as handle:
            handle.write(texts[key])
        os.chmod(path, 0o755)
    _rc, out, _err = _run(module, ["sbatch", "--parsable", f"--chdir={run['code_dir']}", scripts["batch"]])
    job_id = slurm.submitted_id(out)
    if not job_id:
        module.fail_json(msg=f"sbatch printed no job id: {out.strip()}")
    module.exit_json(changed=True, job_id=job_id, scripts=scripts, diff=diff)


def query(module, job_id):
    rc, live, err = _run(module, ["scontrol", "show", "job", "-o", job_id], False)
    down = ""
    if slurm.controller_down(rc, err):
        down = ((err or live).strip().splitlines() or [f"scontrol exited {rc}"])[-1]
    done = ""
    if not slurm.parse_scontrol_job(live):
        # slurmctld has forgotten it (MinJobAge): accounting, or the job completion log
        fields = ["-n", "-P", "-o", slurm.SACCT_FIELDS, "-j", job_id]
        rc, done, _err = _run(module, ["sacct", "-X"] + fields, False)
        if rc != 0 or not slurm.parse_sacct(done, job_id):
            _rc, done, _err = _run(module, ["sacct", "-c"] + fields, False)
    status = slurm.status_of(job_id, live, done, down)
    if status is None:
        module.fail_json(
            msg=f"train_job_id: Slurm knows no job {job_id} (neither slurmctld nor accounting nor the job completion "
            "log). Fix: the id sbatch printed."
        )
    if status["state"] in ("RUNNING", slurm.COMPLETING) and status["nodes"] and not status.get("controller_down"):
        # whether slurmctld hears from the job's nodes (a node that refuses its messages keeps a job COMPLETING)
        rc, text, _err = _run(module, ["scontrol", "show", "node", "-o", status["nodes"]], False)
        nodes = slurm.parse_nodes(text) if rc == 0 else {}
        status.update(node_states=nodes, not_responding=slurm.not_responding(nodes))
    submitted = status.pop("submitted", "")
    if submitted:
        status["submitted_at"] = slurm.epoch(submitted)
    return status


def main():
    module = AnsibleModule(
        argument_spec={
            "state": {
                "type": "str",
                "default": "submitted",
                "choices": ["checked", "submitted", "query", "finished", "cancelled"],
            },
            "job": {"type": "dict"},
            "job_dir": {"type": "path"},
            "job_id": {"type": "str"},
            "wait_timeout": {"type": "int", "default": 0},
            "poll_interval": {"type": "int", "default": 10},
            "outage_timeout": {"type": "int", "default": 600},
            "completing_timeout": {"type": "int", "default": 300},
        },
        required_if=[
            ("state", "checked", ["job"]),
            ("state", "submitted", ["job", "job_dir"]),
            ("state", "query", ["job_id"]),
            ("state", "finished", ["job_id"]),
            ("state", "cancelled", ["job_id"]),
        ],
        supports_check_mode=True,
    )
    p = module.params
    if p["state"] == "checked":
        errors = request_errors(module, p["job"])
        if errors:
            module.fail_json(msg=" ".join(errors), errors=errors)
        module.exit_json(changed=False)
    if p["state"] == "submitted":
        submit(module, slurm.complete(p["job"]), p["job_dir"])
    status = query(module, p["job_id"])
    if p["state"] == "cancelled" and not status["finished"]:
        if not module.check_mode:
            _run(module, ["scancel", p["job_id"]])
        module.exit_json(changed=True, job_id=p["job_id"], **status)
    # query, and finished when the action plugin is not in front (it polls query)
    module.exit_json(changed=False, job_id=p["job_id"], **status)


if __name__ == "__main__":
    main()
