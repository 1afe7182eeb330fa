# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
"""The plan, and with lock given the host's lock taken in the same call (one round trip for both, as
playbooks/deploy.yml plans): names this run to the lock and waits while another run holds it, as the
isaac_sim_lock action does (its hold)."""

from ansible.plugins.action import ActionBase
from ansible_collections.isaacsim.fleet.plugins.plugin_utils.run_hold import hold, this_run


class ActionModule(ActionBase):
    _supports_check_mode = True

    def run(self, tmp=None, task_vars=None):
        result = super().run(tmp, task_vars)
        args = dict(self._task.args)
        # lock given at all (even empty, its options' defaults): this run is named to it
        if args.get("lock") is None:
            result.update(self._execute_module(module_args=args, task_vars=task_vars))
            return result
        lock = dict(args["lock"], holder=this_run(task_vars.get("ansible_play_name", "")))

        def execute(lock_args):
            planned = self._execute_module(module_args=dict(args, lock=lock_args), task_vars=task_vars)
            return planned.get("lock") or {}, planned

        result.update(hold(execute, lock, task_vars.get("inventory_hostname"), self._task.check_mode))
        return result
