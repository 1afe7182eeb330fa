#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_experience
short_description: Run one experience (a compose file judged by its test orchestrators) on a host to its verdict
version_added: "0.3.0"
description:
  - Reads the team's compose file as the fleet runs it; what cannot be honoured is an error and nothing starts,
    what is ignored comes back in RV(ignored).
  - Each service becomes a systemd unit in C(/run/systemd/system) running its container in the foreground, on a
    network and named volumes of the run's own; systemd restarts services by their compose restart policy and
    the journal keeps their logs.
  - The run is judged by the reference platform's rules - any orchestrator exiting non-zero fails it, all
    orchestrators exiting 0 pass it, a non-orchestrator's failure fails it unless it has a restart policy -
    or times out; then every container is stopped and the units, network and volumes are removed.
  - The run's directory on the host keeps each service's log, the compose file as run, metrics over time
    (C(metrics.csv)), C(result.json) and C(junit.xml). A failed verdict is a result, not a module failure.
  - A borrowed instance (O(instance)) is lent through the collection's one lifecycle - the run waits, up to
    O(timeout), for another run that holds it - and given back by it when the run ends, here on the host (a
    controller that went away changes nothing) - restarted clean, ready, then free, so no run ever gets an instance
    that another run used, and nothing else restarts it while it is lent.
  - Run it with C(async) so a long run survives the controller's connection.
author: isaacsim.fleet contributors (@isaacsim-fleet)
extends_documentation_fragment:
  - isaacsim.fleet.attributes
  - isaacsim.fleet.attributes.platform
  - isaacsim.fleet.layout.data_root
  - isaacsim.fleet.runs
attributes:
  check_mode:
    support: partial
    details: Reads the compose file and checks the images, the GPUs and the borrowed instance; nothing is pulled,
      started or tidied, and C(changed) is true. An image not on the host fails the check, though the real run would
      pull it first (O(pull)).
  diff_mode:
    support: none
    details: No diff is returned.
  platform:
    platforms: posix
options:
  compose:
    description: The compose file, parsed (for example C(lookup('file', path) | from_yaml)).
    type: dict
    required: true
  name:
    description: The experience's name (in the run's name, the artefacts and JUnit).
    type: str
    required: true
  environment:
    description:
      - The experience's environment; overrides every service's and is given to each (through a file only root
        reads, never on a command line).
    type: dict
    default: {}
  secret_environment:
    description:
      - More of it, for tokens and passwords - over O(environment), kept out of the logs and out of the compose file
        as run.
    type: dict
    default: {}
  profiles:
    description: The compose profiles the experience runs.
    type: list
    elements: str
    default: []
  run:
    description: The run's name (lower case letters, digits and dashes); made from O(name) and the time when unset.
    type: str
  timeout:
    description: Seconds from the first service's start until the run is stopped and judged C(timeout).
    type: float
    default: 600
  instance:
    description:
      - The Isaac Sim instance the simulator service (C(image=isaac-sim)) borrows; it must be ready and not lent
        to another run. Its address and ports reach every service as C(ISAAC_SIM_HOST) and
        C(ISAAC_SIM_PORT_<NAME>), and the simulator's service name resolves to the host.
    type: int
  simulator:
    description:
      - C(borrow) - the simulator service runs on the fleet instance O(instance).
      - C(dedicated) - the run starts a headless Isaac Sim of its own as the simulator service (O(simulator_image),
        the release's headless launch unless the service gives an entrypoint, NVIDIA's AppReady healthcheck unless
        it gives one), on the run's network under the service's name, with one GPU of O(gpus) unless it asks for
        its own. Its caches are kept per slot under C(DATA_ROOT/simulators/N), so the next run starts warm. No
        instance of the fleet is touched.
    type: str
    choices: [borrow, dedicated]
    default: borrow
  simulator_image:
    description: The dedicated simulator's image; by default the image of the host's deployed instances.
    type: str
  simulator_release:
    description:
      - The dedicated simulator's release (C(2023.1), C(4.x), C(5.x), C(6.x)); by default that of the host's deployed
        instances, else the one the image's tag names.
    type: str
  pull:
    description:
      - Pull the services' images missing on the host, before anything starts; one that cannot be pulled is an error.
    type: bool
    default: true
  poll:
    description: Seconds between two looks at the run's services.
    type: float
    default: 0.5
  metrics_interval:
    description: Seconds between two CPU and memory samples of each running container.
    type: float
    default: 2
notes:
  - Check mode reads the file and checks the images and GPUs on the host; nothing starts.
"""

EXAMPLES = r"""
- name: Run the pick-and-place test against instance 0
  isaacsim.fleet.isaac_sim_experience:
    compose: "{{ lookup('ansible.builtin.file', 'experiences/pick.yml') | from_yaml }}"
    name: pick
    environment: {SEED: "42"}
    instance: 0
    timeout: 900
  async: 1200
  poll: 5

- name: Run it with a headless Isaac Sim of its own (the host's image and release), on GPU 1
  isaacsim.fleet.isaac_sim_experience:
    compose: "{{ lookup('ansible.builtin.file', 'experiences/pick.yml') | from_yaml }}"
    name: pick
    simulator: dedicated
    gpus: ["1"]
  async: 1200
  poll: 5
  register: pick
"""

RETURN = r"""
run:
  description: The run's name.
  returned: always
  type: str
verdict:
  description: C(result) (passed, failed, timeout or error), C(service) that decided it, C(reason), C(seconds).
  returned: when the run started
  type: dict
services:
  description: Per service - orchestrator, started, exit_code (when it had exited at the verdict), restarts.
  returned: when the run started
  type: dict
events:
  description: The run's timeline - [seconds, service, what happened].
  returned: when the run started
  type: list
  elements: list
metrics:
  description: Per service - samples, cpu_peak_percent, cpu_mean_percent (of one core), memory_peak_bytes.
  returned: when the run started
  type: dict
directory:
  description: The run's directory on the host.
  returned: always
  type: str
artefacts:
  description: File names in RV(directory).
  returned: when the run started
  type: list
  elements: str
bundle:
  description:
    - A gzip'd tar on the host of RV(directory) and of each directory in RV(recovered), a directory each by its run's
      name, to bring back; remove it, and then the directories in RV(directories), once the controller has it.
  returned: when the run started
  type: str
directories:
  description: The run directories RV(bundle) holds (this run's and the recovered ones).
  returned: when the run started
  type: list
  elements: str
recovered:
  description: Runs whose controller went away before bringing them back; their directories are in RV(bundle).
  returned: always
  type: list
  elements: str
expired:
  description: Run directories (and bundles nobody fetched) removed because they were older than O(keep_days).
  returned: always
  type: list
  elements: str
ignored:
  description: What the fleet ignores in the file, and why (also given as warnings).
  returned: always
  type: list
  elements: str
borrowed_instance:
  description: The instance the run borrowed (given back, restarted clean, when the module returns); null when none.
  returned: always
  type: int
restart_error:
  description: Why the borrowed instance did not come back after the run (it is not ready, so it is not lent again).
  returned: when its restart failed
  type: str
simulator_slot:
  description: The slot of a dedicated simulator (its caches are in C(DATA_ROOT/simulators/SLOT)).
  returned: when O(simulator=dedicated) and the run started
  type: int
"""

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import runner


def main():
    module = AnsibleModule(
        argument_spec={
            "compose": {"type": "dict", "required": True},
            "name": {"type": "str", "required": True},
            "environment": {"type": "dict", "default": {}},
            "secret_environment": {"type": "dict", "default": {}, "no_log": True},
            "profiles": {"type": "list", "elements": "str", "default": []},
            "run": {"type": "str"},
            "timeout": {"type": "float", "default": 600},
            "instance": {"type": "int"},
            "simulator": {"type": "str", "default": "borrow", "choices": ["borrow", "dedicated"]},
            "simulator_image": {"type": "str"},
            "simulator_release": {"type": "str"},
            **runner.HOST_OPTIONS,
            "pull": {"type": "bool", "default": True},
            "poll": {"type": "float", "default": 0.5},
            "metrics_interval": {"type": "float", "default": 2},
        },
        supports_check_mode=True,
    )
    runner.finish(module, runner.bind(module).experience(module.params))


if __name__ == "__main__":
    main()
