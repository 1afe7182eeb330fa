#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_test_suite
short_description: Run a host's share of a test suite, a bounded number of experiences at a time
version_added: "0.3.0"
description:
  - Runs the given runs (experiences as M(isaacsim.fleet.isaac_sim_experience) runs them) with at most O(parallel)
    at once. A run whose file has the simulator (C(image=isaac-sim)) waits for a free instance of O(instances) and
    borrows it; a run that reserves GPUs waits for that many free ids of O(gpus).
  - Lending is the collection's one lifecycle's (C(module_utils/instance/lifecycle.py)) - a run borrows an instance, and
    after it the instance is restarted clean and ready before it is free again, one at a time; one that does not come
    back is not lent again. A run takes an instance that nobody else holds (a person's session, another suite's
    run) where there is one; an instance held elsewhere is taken only when none is free, and then waited for,
    up to the run's timeout. No restart ever touches an instance lent to another run or a session.
  - One run failing, hanging (it ends at its own timeout) or not starting never stops the others.
  - Use C(async) - a suite takes as long as its runs.
author: isaacsim.fleet contributors (@isaacsim-fleet)
extends_documentation_fragment:
  - isaacsim.fleet.attributes
  - isaacsim.fleet.attributes.platform
  - isaacsim.fleet.layout.data_root
  - isaacsim.fleet.runs
attributes:
  check_mode:
    support: partial
    details: Reads every run's file and checks the images; nothing is pulled, started or tidied, and C(changed) is
      true when there are runs. An image not on the host is reported as one that cannot be had, though the real runs
      would pull it first.
  diff_mode:
    support: none
    details: No diff is returned.
  platform:
    platforms: posix
options:
  runs:
    description:
      - The runs, each with C(key) (short, unique), C(title), C(experience) (name), C(compose) (parsed),
        C(environment), C(profiles), C(timeout), C(gpus) (count), C(simulator) (bool, borrows) and C(dedicated)
        (bool, a simulator of its own, as M(isaacsim.fleet.isaac_sim_experience) starts one with
        O(isaacsim.fleet.isaac_sim_experience#module:simulator=dedicated)), as the suite filter makes them.
    type: list
    elements: dict
    required: true
  parallel:
    description: Runs at once on this host.
    type: int
    default: 2
  instances:
    description: The instances of this host that runs may borrow.
    type: list
    elements: int
    default: []
notes:
  - Check mode reads every file and checks the images; nothing starts.
"""

EXAMPLES = r"""
- name: Run this host's share of the suite
  isaacsim.fleet.isaac_sim_test_suite:
    runs: "{{ my_share }}"
    parallel: 2
    instances: [0, 1]
  async: 7200
  poll: 5
"""

RETURN = r"""
results:
  description:
    - One per run, in the order given - C(title), C(key), C(run), C(host), C(verdict), C(services), C(metrics),
      C(directory), C(artefacts); C(error) when the run could not start, C(restart_error) when its borrowed
      instance did not come back.
  returned: always
  type: list
  elements: dict
bundle:
  description:
    - Every run's directory in one gzipped tar file on the host (a directory per run), with those of RV(recovered),
      to fetch at once; remove it, and then the directories in RV(directories), once the controller has it.
  returned: when the runs ran
  type: str
directories:
  description: The run directories RV(bundle) holds.
  returned: when the runs ran
  type: list
  elements: str
recovered:
  description: Earlier runs whose controller went away before bringing them back; they are in RV(bundle).
  returned: when the runs ran
  type: list
  elements: str
expired:
  description: Run directories (and bundles nobody fetched) removed because they were older than O(keep_days).
  returned: when the runs ran
  type: list
  elements: str
"""

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import runner


def main():
    module = AnsibleModule(
        argument_spec={
            "runs": {"type": "list", "elements": "dict", "required": True},
            "parallel": {"type": "int", "default": 2},
            "instances": {"type": "list", "elements": "int", "default": []},
            **runner.HOST_OPTIONS,
        },
        supports_check_mode=True,
    )
    runner.finish(module, runner.bind(module).share(module.params))


if __name__ == "__main__":
    main()
