#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: nvidia_driver_check
short_description: Check that the NVIDIA driver is present and new enough for an Isaac Sim release
version_added: "0.1.0"
description:
  - Lists the GPUs with C(nvidia-smi) and fails with a clear message when none answers or when the
    driver is older than the minimum of the chosen Isaac Sim release (or O(min_version)).
  - Read-only; always C(changed=false).
author: isaacsim.fleet contributors (@isaacsim-fleet)
extends_documentation_fragment:
  - isaacsim.fleet.attributes
  - isaacsim.fleet.attributes.platform
attributes:
  check_mode:
    support: full
    details: Reads only; the same in check mode.
  diff_mode:
    support: none
    details: Nothing changes, so there is no diff.
  platform:
    platforms: posix
options:
  release:
    description: Isaac Sim release family whose minimum driver applies.
    type: str
    default: "6.x"
    choices: ["2023.1", "4.x", "5.x", "6.x"]
  min_version:
    description: Minimum driver version; overrides the release's.
    type: str
"""

EXAMPLES = r"""
- name: Check the driver for Isaac Sim 5.x
  isaacsim.fleet.nvidia_driver_check:
    release: "5.x"
"""

RETURN = r"""
gpus:
  description: The GPUs found.
  returned: always
  type: list
  elements: dict
  sample: [{"index": 0, "name": "NVIDIA L40S", "memory_total_mib": 46068, "driver": "570.172.08"}]
min_version:
  description: The minimum applied.
  returned: always
  type: str
  sample: "570.169"
"""

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import driver
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import hostprobe
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance.releases import RELEASES


def main():
    module = AnsibleModule(
        argument_spec=dict(
            release=dict(type="str", default="6.x", choices=list(RELEASES)),
            min_version=dict(type="str"),
        ),
        supports_check_mode=True,
    )
    minimum = module.params["min_version"] or RELEASES[module.params["release"]]["min_driver"]
    gpus = []
    if module.get_bin_path("nvidia-smi"):
        rc, out, _err = module.run_command(hostprobe.GPU_QUERY)
        if rc == 0:
            gpus = hostprobe.parse_gpu_list(out)
    error = driver.check(gpus, minimum, module.params["release"])
    if error:
        module.fail_json(msg=error, gpus=gpus, min_version=minimum)
    module.exit_json(changed=False, gpus=gpus, min_version=minimum)


if __name__ == "__main__":
    main()
