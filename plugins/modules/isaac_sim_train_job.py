#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_train_job
short_description: Submit, follow and cancel an Isaac Lab training job on a Slurm cluster
version_added: "0.3.0"
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
extends_documentation_fragment:
  - isaacsim.fleet.attributes
  - isaacsim.fleet.attributes.platform
  - isaacsim.fleet.attributes.action
attributes:
  action:
    support: full
    details: With O(state=finished) and O(state=cancelled), follows the job from the controller, printing a line
      whenever it changes.
  check_mode:
    support: full
    details: O(state=submitted) returns the scripts it would write and submits nothing, O(state=cancelled) cancels
      nothing; the other states only read.
  diff_mode:
    support: partial
    details: With O(state=submitted), the new job's batch and node scripts; its snapshot of the code is not shown.
  platform:
    platforms: posix
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

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.train import job

ARGUMENT_SPEC = {
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
}
REQUIRED_IF = [
    ("state", "checked", ["job"]),
    ("state", "submitted", ["job", "job_dir"]),
    ("state", "query", ["job_id"]),
    ("state", "finished", ["job_id"]),
    ("state", "cancelled", ["job_id"]),
]


def main():
    module = AnsibleModule(argument_spec=ARGUMENT_SPEC, required_if=REQUIRED_IF, supports_check_mode=True)
    try:
        result = job.LoginNode(module.run_command, module.check_mode).act(module.params)
    except job.JobError as exc:
        module.fail_json(msg=str(exc), **exc.result)
    module.exit_json(**result)


if __name__ == "__main__":
    main()
