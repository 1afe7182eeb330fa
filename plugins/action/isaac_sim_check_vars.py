# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
"""Checks the types of the variables set for the given hosts against the argument specs of every
role of the collection, before any role runs (playbooks/inventory_check.yml): a wrong type is one
line naming the variable, its value, what it must be and the fix, and nothing changes anywhere.
Runs on the controller only."""

from pathlib import Path

import yaml
from ansible.errors import AnsibleError
from ansible.plugins.action import ActionBase
from ansible_collections.isaacsim.fleet.plugins.module_utils.common import varcheck

ROLES = Path(__file__).resolve().parents[2] / "roles"


class ActionModule(ActionBase):
    TRANSFERS_FILES = False
    _supports_check_mode = True

    def run(self, tmp=None, task_vars=None):
        result = super().run(tmp, task_vars)
        hosts = list(self._task.args.get("hosts") or [])
        documents = [yaml.safe_load(p.read_text()) for p in sorted(ROLES.glob("*/meta/argument_specs.yml"))]
        specs = varcheck.merged_specs(documents)
        found = {}
        for host in hosts:
            their = task_vars["hostvars"][host]
            values = {}
            for name in specs:
                try:
                    if name in their:
                        values[name] = their[name]
                except AnsibleError:
                    continue  # a template that fails: the role reports it where it is used
            for problem in varcheck.problems(specs, values):
                found.setdefault(problem, []).append(host)
        result["changed"] = False
        if found:
            lines = [
                f"- {problem} ({'every host' if len(on) == len(hosts) else 'hosts: ' + ', '.join(on)})"
                for problem, on in found.items()
            ]
            result["failed"] = True
            result["msg"] = "Variables of the wrong type; nothing was changed on any host.\n" + "\n".join(lines)
        return result
