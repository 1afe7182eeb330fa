#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_mirror_info
short_description: Read the health and storage of the fleet's registry mirror
version_added: "0.3.0"
description:
  - Runs on the host of the registry mirror (role C(registry_mirror)) and says whether its unit runs, whether its
    registry answers (the registry answers 503 when its storage fails), the images its storage holds per repository,
    the bytes they take and what is left on the disk under them.
  - Only reads; the same in check mode.
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
    platforms: debian
    details: The registry of Debian's C(docker-registry) package - its storage.
options:
  min_free_gb:
    description: Free space on the storage's disk, in GiB, below which the mirror is marked low on space (it still
      serves; the next image may not fit).
    type: float
    default: 20
"""

EXAMPLES = r"""
- name: Read the mirror's state
  isaacsim.fleet.isaac_sim_mirror_info:
  register: mirror
"""

RETURN = r"""
mirror:
  description: The mirror's state.
  returned: always
  type: dict
  contains:
    healthy:
      description: The unit runs and the registry answers.
      type: bool
    active:
      description: The unit's state (C(systemctl is-active)).
      type: str
    http_status:
      description: What the registry answered to C(GET /v2/) on the loopback (none when it did not answer).
      type: int
    repositories:
      description: Per repository, the number of manifests its storage holds.
      type: dict
    images:
      description: Manifests held in all.
      type: int
    used_bytes:
      description: Bytes of the mirror's storage.
      type: int
    free_bytes:
      description: Bytes left on the disk of the storage.
      type: int
    size_bytes:
      description: Size of that disk.
      type: int
    errors:
      description: What is wrong, each with its fix where there is one.
      type: list
      elements: str
    low_space:
      description: Less than O(min_free_gb) is free on the storage's disk.
      type: bool
    warnings:
      description: What is not wrong yet but will be (low on space), each with its fix.
      type: list
      elements: str
"""

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import mirror_info


def main():
    module = AnsibleModule(argument_spec=dict(min_free_gb=dict(type="float", default=20)), supports_check_mode=True)
    mirror = mirror_info.collect(module.run_command, min_free_gb=module.params["min_free_gb"])
    module.exit_json(changed=False, mirror=mirror)


if __name__ == "__main__":
    main()
