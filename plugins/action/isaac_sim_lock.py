# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
"""Names this playbook run to the host's lock (the module isaac_sim_lock) and waits while another
run holds it (plugin_utils/run_hold.py)."""

from ansible.plugins.action import ActionBase
from ansible_collections.isaacsim.fleet.plugins.plugin_utils.run_hold import hold, this_run


class ActionModule(ActionBase):
    _supports_check_mode = True

    def run(self, tmp=None, task_vars=None):
        result = super().run(tmp, task_vars)
        args = dict(self._task.args, holder=this_run(task_vars.get("ansible_play_name", "")))

        def execute(lock):
            looked = self._execute_module(module_args=lock, task_vars=task_vars)
            return looked, looked

        result.update(hold(execute, args, task_vars.get("inventory_hostname"), self._task.check_mode))
        return result
