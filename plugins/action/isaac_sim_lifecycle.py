# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
"""Runs the lifecycle module on the host as a background job and waits for it from here,
renewing this run's hold on the host (the lock) every few seconds: the heartbeat that tells
the host the controller is still there. When the controller goes away (Ctrl-C, killed, its
connection lost) the renewals stop, and the lifecycle stops before its next instance instead
of rolling the rest of the host unwatched (isaac_sim_lifecycle's controller_run). A task with
its own async is run as Ansible runs any module with it, not tied to the lock.

An apply first looks in check mode, in the task (one round trip): where it finds nothing to change,
as on an idempotent deploy's re-run, that answer is the task's (lifecycle.apply returns the same
result for a check and for a real call with nothing to do) and no job is started. A look that
fails is the task's failure too: the real call fails the same way, before any change."""

import time

from ansible.plugins.action import ActionBase
from ansible_collections.isaacsim.fleet.plugins.plugin_utils.run_hold import this_run

# soon at first: most calls (an idempotent deploy, a stop) end within a second
POLL_S = (0.25, 0.25, 0.5, 1, 1, 2, 2, 3)
POLL_MAX_S = 5
# the lock renewed before a poll once this many seconds have passed since the last renewal, by
# the clock (a poll under load takes seconds of its own): well inside runlock.HEARTBEAT_LIMIT_S
# (30 s), with room for a slow connection
RENEW_S = 5
# the background job's own limit; the lifecycle's steps have their own deadlines
JOB_LIMIT_S = 24 * 3600
_JOB_KEYS = ("ansible_job_id", "started", "finished", "results_file", "stdout_lines", "stderr_lines")


class ActionModule(ActionBase):
    _supports_check_mode = True
    _supports_async = True

    def run(self, tmp=None, task_vars=None):
        result = super().run(tmp, task_vars)
        args = dict(self._task.args)
        if self._task.async_val:
            # the task's own async: Ansible polls the job by its id (or leaves it, poll: 0), as for any
            # module. No renewals come from here meanwhile, so the job is not tied to this run's lock.
            wrap_async = not self._connection.has_native_async
            result.update(self._execute_module(module_args=args, task_vars=task_vars, wrap_async=wrap_async))
            if not wrap_async:
                self._remove_tmp_path(self._connection._shell.tmpdir)
            return result
        me = this_run(task_vars.get("ansible_play_name", ""))
        args["controller_run"] = me["id"]
        if self._task.check_mode:
            result.update(self._execute_module(module_args=args, task_vars=task_vars))
            return result
        if args.get("action", "apply") == "apply":
            looked = self._look(args, task_vars)
            if looked.get("failed") or not looked.get("changed"):
                result.update(looked)
                return result
        self._task.async_val = JOB_LIMIT_S
        try:
            started = self._execute_module(module_args=args, task_vars=task_vars, wrap_async=True)
        finally:
            self._task.async_val = 0
        if started.get("failed") or not started.get("ansible_job_id"):
            result.update(started)
            return result
        jid = started["ansible_job_id"]
        async_dir = self._remote_expand_user(self.get_shell_option("async_dir", default="~/.ansible_async"))
        polls, renewed = 0, time.monotonic()
        while True:
            wait = POLL_S[polls] if polls < len(POLL_S) else POLL_MAX_S
            time.sleep(wait)
            polls += 1
            if time.monotonic() - renewed >= RENEW_S:
                renewed = time.monotonic()
                self._execute_module(
                    module_name="isaacsim.fleet.isaac_sim_lock",
                    module_args={"holder": me, "state": "renewed"},
                    task_vars=task_vars,
                )
            status = self._execute_module(
                module_name="ansible.legacy.async_status",
                module_args={"jid": jid, "_async_dir": async_dir},
                task_vars=task_vars,
            )
            if status.get("finished") or (status.get("failed") and not status.get("started")):
                break
        self._execute_module(
            module_name="ansible.legacy.async_status",
            module_args={"jid": jid, "mode": "cleanup", "_async_dir": async_dir},
            task_vars=task_vars,
        )
        self._remove_tmp_path(self._connection._shell.tmpdir)
        result.update({k: v for k, v in status.items() if k not in _JOB_KEYS})
        return result

    def _look(self, args, task_vars):
        """The module in check mode, in the task: what the call would change."""
        self._task.check_mode = True
        try:
            return self._execute_module(module_args=args, task_vars=task_vars)
        finally:
            self._task.check_mode = False
