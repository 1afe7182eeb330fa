#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_warm_cache
short_description: Give instances that would start on empty caches a cache warmed once for the fleet
version_added: "0.3.0"
description:
  - A cache is valid for a key - the release, the image (its id), the instance's profile, the GPU model and the
    driver version.
  - C(state=probe) finds the planned instances that are not running and whose cache directories hold no file,
    with the key each needs, and the keys whose archive the host keeps.
  - C(state=warm) makes the archive of one key on this host - a one-off container of the first such instance
    (its image, arguments and GPU, Docker's bridge network, every mount on scratch directories) runs until the
    release's ready line, is stopped cleanly, and what its cache mounts hold is kept.
  - C(state=seed) unpacks the archive of each such instance's key, where the host keeps it, into its cache
    directories, owned by the container's user. A running instance, or one with any cached file, is left alone.
    A seed that fails for an instance is a warning, and that instance starts cold; a broken archive is removed.
  - C(state=probe) also removes a warm run a killed deploy left behind.
  - Nothing here starts, stops or restarts an instance; the lifecycle starts them afterwards.
author: isaacsim.fleet contributors (@isaacsim-fleet)
extends_documentation_fragment:
  - isaacsim.fleet.attributes
  - isaacsim.fleet.attributes.platform
attributes:
  check_mode:
    support: full
    details: Finds the instances that would start cold and the keys, and says what would change; nothing is warmed,
      seeded or removed.
  diff_mode:
    support: none
    details: No diff is returned.
  platform:
    platforms: posix
options:
  state:
    description: What to do.
    type: str
    choices: [probe, warm, seed]
    default: probe
  plan:
    description: The host's plan (M(isaacsim.fleet.isaac_sim_plan)).
    type: dict
    required: true
  image_id:
    description: The id of the image the instances run (C(sha256:...)); C(unknown) finds nothing cold.
    type: str
    required: true
  gpus:
    description: The host's GPUs as the plan's probe found them (C(index), C(name)).
    type: list
    elements: dict
    default: []
  driver:
    description: The host's NVIDIA driver version.
    type: str
    default: ""
  key:
    description: With C(state=warm), the id of the key to warm.
    type: str
"""

EXAMPLES = r"""
- name: Find the instances that would start cold
  isaacsim.fleet.isaac_sim_warm_cache:
    plan: "{{ __isaac_sim_plan }}"
    image_id: "{{ __isaac_sim_image_id }}"
    gpus: "{{ __isaac_sim_host.gpus }}"
    driver: "{{ __isaac_sim_host.gpu_driver }}"
  register: warm
"""

RETURN = r"""
cold:
  description: Key id to the ids of the instances that would start on empty caches.
  returned: always
  type: dict
keys:
  description: Key id to the key (C(release), C(image_id), C(gpu_model), C(driver)).
  returned: always
  type: dict
held:
  description: The key ids whose archive the host keeps.
  returned: always
  type: list
  elements: str
store:
  description: The directory of the host's archives.
  returned: always
  type: str
ready_after_s:
  description: With C(state=warm), the seconds the warm run took to its ready line (a cold start's time).
  returned: when a cache was warmed
  type: float
bytes:
  description: With C(state=warm), the archive's size.
  returned: when a cache was warmed
  type: int
seeded:
  description: With C(state=seed), instance id to the number of files it was given.
  returned: when state is seed
  type: dict
"""

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import warm_cache


def main():
    module = AnsibleModule(
        argument_spec=dict(
            state=dict(type="str", choices=["probe", "warm", "seed"], default="probe"),
            plan=dict(type="dict", required=True),
            image_id=dict(type="str", required=True),
            gpus=dict(type="list", elements="dict", default=[]),
            driver=dict(type="str", default=""),
            key=dict(type="str", no_log=False),
        ),
        required_if=[("state", "warm", ["key"])],
        supports_check_mode=True,
    )
    p = module.params
    try:
        result = warm_cache.call(p, module.check_mode, module.run_command)
    except (warm_cache.WarmError, OSError, KeyError) as exc:
        module.fail_json(msg=f"warming the instances' caches: {exc}")
    for warning in result.pop("warnings", []):
        module.warn(warning)
    module.exit_json(**result)


if __name__ == "__main__":
    main()
