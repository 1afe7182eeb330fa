#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_mirror_seed
short_description: Copy the fleet's pinned images into its registry mirror once, before any host pulls
version_added: "0.3.0"
description:
  - Runs on the host of the registry mirror (role C(registry_mirror)). For each image pinned on the mirror
    (C(MIRROR/REPOSITORY@DIGEST)) that its storage does not hold whole, copies it from the mirror's upstream
    with C(skopeo copy --all --preserve-digests), byte for byte, into the mirror's own storage, through a
    writable registry of the same package started on the loopback for the copy's time alone.
  - The proxy then serves the image from its storage and asks the upstream nothing, so the fleet costs the
    upstream the image once (a proxy asked first fetches each blob twice).
  - The upstream's credentials are read from the mirror's config; for the copy they are in a root-only file on
    C(/run), removed after it, failed or not.
  - An image held whole already is left alone (changed false). Check mode says what would be copied.
  - One change of the mirror's storage at a time - a seed waits while another run seeds or collects garbage.
  - With O(ask), asks the upstream itself (never the mirror's cached copy) which digest each C(NAME:TAG) names
    now, with the mirror's own credentials - the deploy's pin compares it with the mirror's answer, so that a tag
    the upstream withdrew stops the deploy (C(isaac_sim_image_pin)).
author: isaacsim.fleet contributors (@isaacsim-fleet)
extends_documentation_fragment:
  - isaacsim.fleet.attributes
  - isaacsim.fleet.attributes.platform
  - isaacsim.fleet.mirror_lock
attributes:
  check_mode:
    support: full
    details: Says what would be copied; nothing is copied. O(ask) asks the upstream as outside check mode.
  diff_mode:
    support: none
    details: No diff is returned.
  platform:
    platforms: debian
    details: The registry of Debian's C(docker-registry) package - its user, program and storage.
options:
  references:
    description:
      - The references the hosts pull, C(MIRROR/REPOSITORY@sha256:DIGEST), as C(isaac_sim_image_pin) pinned them.
    type: list
    elements: str
    default: []
  ask:
    description:
      - Images as the user wrote them (C(nvcr.io/nvidia/isaac-sim:6.0.1)); each one the hosts pull by tag through
        this mirror is asked of the mirror's upstream with C(skopeo inspect --raw) (one manifest request each).
        Nothing is copied for them.
    type: list
    elements: str
    default: []
  mirror:
    description: The mirror as the hosts name it, C(HOST:PORT).
    type: str
    required: true
  ready_timeout:
    description: Seconds to wait for the loopback registry to answer.
    type: int
    default: 30
"""

EXAMPLES = r"""
- name: Copy the pinned image into the mirror
  isaacsim.fleet.isaac_sim_mirror_seed:
    references: ["10.20.0.9:5443/nvidia/isaac-sim@sha256:0a1b..."]
    mirror: "10.20.0.9:5443"
  delegate_to: mirror-01
  run_once: true
"""

RETURN = r"""
copied:
  description: The references copied from the upstream by this run (in check mode, those it would copy).
  returned: success
  type: list
  elements: str
held:
  description: The references the mirror held whole already.
  returned: success
  type: list
  elements: str
upstream:
  description:
    - For each image of O(ask) on the mirror's upstream, the upstream's answer - C(digest) (the sha256 of the
      manifest it serves now), or C(cause) (C(missing) - no such tag there, C(login), C(unreachable), or empty) and
      C(said) (skopeo's words, without the key); C(url) the upstream.
  returned: success
  type: dict
"""

import pwd

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import mirror_lock, mirror_seed, registry_mirror


def main():
    module = AnsibleModule(
        argument_spec=dict(
            references=dict(type="list", elements="str", default=[]),
            ask=dict(type="list", elements="str", default=[]),
            mirror=dict(type="str", required=True),
            ready_timeout=dict(type="int", default=30),
            lock_timeout=dict(type="int", default=3600),
        ),
        supports_check_mode=True,
    )
    p = module.params

    def run(argv):
        return module.run_command(argv)

    def run_bytes(argv):
        return module.run_command(argv, encoding=None)

    upstream = {}
    try:
        if p["ask"]:
            upstream = mirror_seed.Seeder(run).ask(p["ask"], p["mirror"], run_bytes)
        images = mirror_seed.wanted(p["references"], p["mirror"])
        seeder = mirror_seed.Seeder(run)
        copied, held = [], []
        if images:
            with mirror_lock.held("a seed of the pinned images", p["lock_timeout"]):
                copied, held = _seed(module, seeder, images, p)
    except (mirror_seed.SeedError, mirror_lock.MirrorBusyError, KeyError) as exc:
        module.fail_json(msg=str(exc))
    module.exit_json(changed=bool(copied), copied=copied, held=held, upstream=upstream)


def _seed(module, seeder, images, p):
    """Under the mirror's lock: what the storage lacks (another run may have copied it meanwhile), copied."""
    lacking = seeder.lacking(images)
    name = {image: f"{p['mirror']}/{image[0]}@{image[1]}" for image in images}
    copied = [name[image] for image in images if image in lacking]
    held = [name[image] for image in images if image not in lacking]
    if lacking and not module.check_mode:
        user = pwd.getpwnam(registry_mirror.USER)
        seeder.copy([image for image in images if image in lacking], user.pw_uid, user.pw_gid, p["ready_timeout"])
        still = seeder.lacking(images)
        if still:
            raise mirror_seed.SeedError(
                "after the copy the mirror's storage still lacks "
                + "; ".join(f"{name[image]}: {', '.join(gaps[:3])}" for image, gaps in still.items())
                + f" (under {mirror_seed.STORE}). Fix: see the mirror's journal (journalctl -u {mirror_seed.UNIT})."
            )
    return copied, held


if __name__ == "__main__":
    main()
