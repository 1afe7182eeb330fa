# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
"""One suite at a time writes a results directory on the controller: two suites given the same
test_suite_dir would overwrite each other's suite.json, junit.xml and bundles. The holder is the
ansible-playbook run (as for the hosts' lock); one whose process is gone gives it up at once."""

import os
import time

from ansible.plugins.action import ActionBase
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import runlock
from ansible_collections.isaacsim.fleet.plugins.plugin_utils.run_hold import alive, this_run

LOCK_NAME = ".suite-lock.json"
# the module's documented options (plugins/modules/isaac_sim_results_lock.py), checked as Ansible checks a
# module's: a misspelt state never takes the directory it meant to give back, and ~ is the user's home
ARGUMENT_SPEC = {
    "path": {"type": "path", "required": True},
    "state": {"type": "str", "choices": ["held", "absent"], "default": "held"},
    "variable": {"type": "str", "default": "path"},
}


class ActionModule(ActionBase):
    _supports_check_mode = True
    TRANSFERS_FILES = False

    def run(self, tmp=None, task_vars=None):
        result = super().run(tmp, task_vars)
        _validation, args = self.validate_argument_spec(ARGUMENT_SPEC)
        directory = str(args.get("path") or "")
        variable = str(args.get("variable") or "path")
        if not directory:
            return dict(result, failed=True, msg=f"{variable} is empty. Fix: give the results directory.")
        me = this_run(task_vars.get("ansible_play_name", ""))
        path, guard = os.path.join(directory, LOCK_NAME), os.path.join(directory, ".suite-lock")
        if args["state"] == "absent":
            released = os.path.isdir(directory) and runlock.release(me, path, guard)
            return dict(result, changed=False, released=released)
        if self._task.check_mode and not os.path.isdir(directory):
            return dict(result, changed=False, acquired=False)
        os.makedirs(directory, exist_ok=True)
        current = runlock.read(path) or {}
        dead = ""
        if current.get("controller") == me["controller"] and not alive(current.get("pid"), current.get("started")):
            dead = current.get("id", "")
        acquired, holder, note = runlock.acquire(
            me, time.time(), 0, dead=dead, path=path, guard=guard, record_path=os.path.join(directory, ".none")
        )
        if not acquired:
            who = runlock.holder_text(holder, time.time())
            return dict(
                result,
                failed=True,
                holder=holder,
                msg=(
                    f"{variable}: {directory} is being written by another suite ({who}); two suites there would "
                    f"overwrite each other's suite.json and junit.xml. Fix: give this one its own directory "
                    f"(-e {variable}=...), or run it when that one has ended."
                ),
            )
        return dict(result, changed=False, acquired=True, note=note)
