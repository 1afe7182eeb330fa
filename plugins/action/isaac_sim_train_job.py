# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
"""Follows a Slurm job from the controller: the module looks once (state=query), this plugin
looks again every poll_interval and prints a line whenever the job's state, time or nodes change,
so a person sees a long training move instead of one silent task. A job that stays COMPLETING
past completing_timeout fails the follow with the nodes it waits for (stuck_nodes)."""

import time

from ansible.plugins.action import ActionBase
from ansible.utils.display import Display
from ansible_collections.isaacsim.fleet.plugins.module_utils.common import parse
from ansible_collections.isaacsim.fleet.plugins.module_utils.train import slurm

display = Display()


class ActionModule(ActionBase):
    _supports_check_mode = True

    def run(self, tmp=None, task_vars=None):
        result = super().run(tmp, task_vars)
        args = dict(self._task.args)
        state = args.get("state", "submitted")
        if state not in ("finished", "cancelled"):
            result.update(self._execute_module(module_args=args, task_vars=task_vars))
            return result
        changed = False
        if state == "cancelled":
            first = self._execute_module(module_args=args, task_vars=task_vars)
            if first.get("failed") or first.get("finished") or self._task.check_mode:
                result.update(first)
                return result
            changed = True
        timeout, poll = int(args.get("wait_timeout") or 0), max(1, int(args.get("poll_interval") or 10))
        outage = int(args.pop("outage_timeout", None) or 600)
        completing = parse.as_int(args.pop("completing_timeout", 300))
        if completing is None or completing < 1:
            result.update(
                failed=True,
                msg=f"completing_timeout: {completing if completing is not None else 'not a number'}. Fix: seconds a "
                "job may stay COMPLETING, 1 or more (train_completing_timeout).",
            )
            return result
        query = dict(args, state="query")
        started, progress, last, down_since, completing_since = time.monotonic(), [], None, None, None
        while True:
            looked = self._execute_module(module_args=query, task_vars=task_vars)
            if looked.get("failed"):
                result.update(looked)
                return result
            # slurmctld away (a restart, a failover): the job goes on without it; waited out, bounded
            if looked.get("controller_down"):
                down_since = down_since or time.monotonic()
                if time.monotonic() - down_since >= outage:
                    result.update(
                        looked,
                        failed=True,
                        progress=progress,
                        msg=f"slurmctld has not answered for {outage} s ({looked.get('reason')}); job "
                        f"{args['job_id']} may go on. Fix: bring slurmctld back, then follow the job again with "
                        "train_job_id (or raise train_outage_timeout).",
                    )
                    return result
            else:
                down_since = None
            line = slurm.progress_line(looked)
            if line != last:
                display.display(f"{self._task.delegate_to or task_vars.get('inventory_hostname')}: {line}")
                progress.append(line)
                last = line
            if looked.get("finished"):
                break
            # ended by slurmctld, and a node does not say its end is done (a munge key not the controller's)
            if looked.get("state") == slurm.COMPLETING:
                completing_since = completing_since or time.monotonic()
                stuck_for = int(time.monotonic() - completing_since)
                if stuck_for >= completing:
                    nodes = slurm.stuck_nodes(looked.get("node_states") or {}) or [looked.get("nodes") or "?"]
                    result.update(
                        looked,
                        failed=True,
                        progress=progress,
                        stuck_nodes=nodes,
                        stuck_for=stuck_for,
                        msg=slurm.stuck_line(looked, stuck_for, nodes) + ". Fix: see journalctl -u slurmd -u munge on "
                        f"{', '.join(nodes)}: a node whose munge key is not the controller's refuses slurmctld's "
                        "messages (playbooks/cluster.yml gives every node the controller's key). The job is not "
                        f"cancelled; follow it again with train_job_id={args['job_id']}.",
                    )
                    return result
            else:
                completing_since = None
            if timeout and time.monotonic() - started >= timeout:
                result.update(
                    looked,
                    failed=True,
                    progress=progress,
                    msg=f"job {args['job_id']} has not ended after {timeout} s ({line}); it goes on. Fix: follow "
                    "it again with train_job_id, or raise train_wait_timeout.",
                )
                return result
            time.sleep(poll)
        result.update(looked, changed=changed, progress=progress)
        return result
