#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_mirror_gc
short_description: Delete from the fleet's registry mirror every image the fleet does not run
version_added: "0.3.0"
description:
  - Runs on the host of the registry mirror (role C(registry_mirror)); C(playbooks/registry_mirror_gc.yml) gives it
    the digests every instance of the fleet runs or is pinned to.
  - Every manifest in the mirror's storage that is none of O(keep) (nor an image of a kept index) is dropped with the
    tags naming it, then the registry's own C(garbage-collect) deletes the blobs no remaining manifest references.
    The mirror is stopped meanwhile and started again, failed or not.
  - Nothing to drop changes nothing. Check mode says what would be dropped.
author: isaacsim.fleet contributors (@isaacsim-fleet)
extends_documentation_fragment:
  - isaacsim.fleet.attributes
  - isaacsim.fleet.attributes.platform
  - isaacsim.fleet.mirror_lock
attributes:
  check_mode:
    support: full
    details: Says what would be dropped; the mirror is neither stopped nor changed (its lock is held while the storage
      is read).
  diff_mode:
    support: none
    details: No diff is returned.
  platform:
    platforms: debian
    details: The registry of Debian's C(docker-registry) package - its user, program and storage.
options:
  keep:
    description: The manifest digests (C(sha256:...)) to keep, in any repository.
    type: list
    elements: str
    required: true
"""

EXAMPLES = r"""
- name: Keep what the fleet runs
  isaacsim.fleet.isaac_sim_mirror_gc:
    keep: ["sha256:0a1b..."]
"""

RETURN = r"""
dropped:
  description: The images dropped (in check mode, those that would be), C(REPOSITORY@DIGEST).
  returned: success
  type: list
  elements: str
freed_bytes:
  description: Bytes the storage shrank by (0 in check mode).
  returned: success
  type: int
"""

import re

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import mirror_gc, mirror_lock

_DIGEST = re.compile(r"^sha256:[0-9a-f]{64}\Z")


def main():
    module = AnsibleModule(
        argument_spec=dict(
            keep=dict(type="list", elements="str", required=True),
            lock_timeout=dict(type="int", default=3600),
        ),
        supports_check_mode=True,
    )
    bad = [d for d in module.params["keep"] if not _DIGEST.match(d)]
    if bad:
        module.fail_json(msg=f"keep: {', '.join(bad)} not a digest (sha256:<64 hex>). Fix: pass manifest digests.")
    collector = mirror_gc.Collector(module.run_command)
    dropped, freed = [], 0
    try:
        # a seed running meanwhile would copy what the plan below takes for unused
        with mirror_lock.held("a garbage collection", module.params["lock_timeout"]):
            images = collector.plan(module.params["keep"])
            dropped = [f"{name}@{digest}" for name, digest in images]
            if images and not module.check_mode:
                freed = collector.collect(images)
    except (mirror_gc.GcError, mirror_lock.MirrorBusyError) as exc:
        module.fail_json(msg=str(exc), dropped=dropped)
    module.exit_json(changed=bool(dropped), dropped=dropped, freed_bytes=freed)


if __name__ == "__main__":
    main()
