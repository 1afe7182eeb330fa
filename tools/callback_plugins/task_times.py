# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Callback for the benchmarks and for finding where a test run's time goes: each task's wall time,
written as JSON to $TASK_TIMES_FILE at the end of the play ([{"task", "path", "seconds", "status"}],
in the order they ran). Not a test."""

from __future__ import annotations

import json
import os
import time

from ansible.plugins.callback import CallbackBase

DOCUMENTATION = r"""
name: task_times
type: aggregate
short_description: Each task's wall time, as JSON, for the benchmarks
description:
  - Writes the tasks of a run with their wall time to the file named by the environment variable TASK_TIMES_FILE.
requirements:
  - enable in configuration (ANSIBLE_CALLBACKS_ENABLED=task_times)
"""


class CallbackModule(CallbackBase):
    CALLBACK_VERSION = 2.0
    CALLBACK_TYPE = "aggregate"
    CALLBACK_NAME = "task_times"
    CALLBACK_NEEDS_ENABLED = True

    def __init__(self):
        super().__init__()
        self.tasks = []
        self._started = None

    def _close(self):
        if self._started is not None:
            self.tasks[-1]["seconds"] = round(time.monotonic() - self._started, 3)
            self._started = None

    def _start(self, task, kind="task"):
        self._close()
        self.tasks.append({"task": task.get_name(), "path": task.get_path() or "", "kind": kind, "status": "skipped"})
        self._started = time.monotonic()

    def v2_playbook_on_play_start(self, play):
        self._close()
        self.tasks.append({"task": f"play: {play.get_name()}", "path": "", "kind": "play", "status": "ok"})
        self._started = time.monotonic()

    def v2_playbook_on_task_start(self, task, is_conditional):
        self._start(task)

    def v2_playbook_on_handler_task_start(self, task):
        self._start(task, "handler")

    def v2_runner_on_ok(self, result):
        self.tasks[-1]["status"] = "changed" if result._result.get("changed") else "ok"

    def v2_runner_on_failed(self, result, ignore_errors=False):
        self.tasks[-1]["status"] = "failed"

    def v2_playbook_on_stats(self, stats):
        self._close()
        path = os.environ.get("TASK_TIMES_FILE")
        if path:
            with open(path, "w") as fh:
                json.dump(self.tasks, fh)
