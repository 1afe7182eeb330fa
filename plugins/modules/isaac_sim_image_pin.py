#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_image_pin
short_description: Resolve an image tag to the digest it names now, once for the whole fleet
version_added: "0.3.0"
description:
  - Asks the image's registry, through this host's Docker daemon (its registry settings, mirrors and
    certificates), which manifest digest a tag names now, so every host of a deploy pulls and runs
    that one digest, C(REPOSITORY@DIGEST), whatever the tag does in the middle of the run.
  - The credentials reach the daemon in the request's C(X-Registry-Auth) header for this one call; no
    file on the host gets them.
  - An image already named by digest is returned as written, without asking. It only reads, and runs
    the same in check mode.
author: isaacsim.fleet contributors (@isaacsim-fleet)
extends_documentation_fragment:
  - isaacsim.fleet.attributes
  - isaacsim.fleet.attributes.platform
attributes:
  check_mode:
    support: full
    details: Only asks the registries; the same in check mode.
  diff_mode:
    support: none
    details: Nothing on the host changes, so there is no diff.
  platform:
    platforms: posix
options:
  images:
    description:
      - Per host of the play, the image its plan runs, as the user wrote it (C(nvcr.io/nvidia/isaac-sim:6.0.1)).
        Each distinct image is asked once.
    type: dict
    required: true
  configured:
    description: Per host, what its instances run now (the references of their env files), to say whom the deploy moves.
    type: dict
    default: {}
  registry_username:
    description: The registry user (C($oauthtoken) for NGC).
    type: str
    default: ""
  registry_password:
    description: The registry password or API key; empty asks without credentials.
    type: str
    default: ""
  asked_from:
    description: The host asked through, as the inventory names it (for the messages).
    type: str
    default: ""
  mirror:
    description:
      - A pull-through mirror (C(HOST:PORT), role C(registry_mirror)) of O(mirror_upstream); images of that registry
        are pinned to the digest the upstream itself names now (O(upstream), or asked through this host's Docker where
        no inventory host runs the mirror), on the mirror's reference, so the hosts pull them from there. The mirror
        alone is not asked - its proxy answers a tag the upstream withdrew from its cached copy.
      - A tag the upstream no longer has fails the module before any change, naming the tag and the registry.
    type: str
    default: ""
  mirror_upstream:
    description: The registry the mirror proxies, as a URL or a host.
    type: str
    default: ""
  upstream:
    description:
      - The upstream's answers as the mirror's host asked them (M(isaacsim.fleet.isaac_sim_mirror_seed)'s C(upstream))
        - per image as written, C(digest), or C(cause) and C(said). Omitted - no inventory host runs the mirror.
    type: dict
  offline:
    description:
      - Where the upstream cannot be asked at all (down, unreachable, the key refused), pin to the mirror's copy of the
        tag (a C(HEAD) of its manifest on the mirror, trusting the system's CAs and Docker's
        C(certs.d/HOST:PORT/ca.crt)), and say which digest. Off - the module fails instead.
    type: bool
    default: false
  docker_socket:
    description: The Docker daemon's socket.
    type: path
    default: /var/run/docker.sock
"""

EXAMPLES = r"""
- name: Pin the fleet's image to one digest
  isaacsim.fleet.isaac_sim_image_pin:
    images: {gpu-01: "nvcr.io/nvidia/isaac-sim:6.0.1", gpu-02: "nvcr.io/nvidia/isaac-sim:6.0.1"}
    configured: {gpu-01: [], gpu-02: ["nvcr.io/nvidia/isaac-sim@sha256:0a1b..."]}
    registry_username: $oauthtoken
    registry_password: "{{ isaac_sim_registry_password }}"
  run_once: true
"""

RETURN = r"""
pinned:
  description: Per host, the reference it pulls and runs, C(REPOSITORY@DIGEST).
  returned: success
  type: dict
  sample: {gpu-01: "nvcr.io/nvidia/isaac-sim@sha256:0a1b..."}
digests:
  description: Per image as written, the manifest digest its tag named when it was asked.
  returned: success
  type: dict
summary:
  description: Per image, a line naming the hosts this deploy moves to it, those that run it already and the new ones.
  returned: success
  type: list
  elements: str
"""

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerSocket
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import image_pin


def main():
    module = AnsibleModule(
        argument_spec=dict(
            images=dict(type="dict", required=True),
            configured=dict(type="dict", default={}),
            registry_username=dict(type="str", default=""),
            registry_password=dict(type="str", default="", no_log=True),
            asked_from=dict(type="str", default=""),
            mirror=dict(type="str", default=""),
            mirror_upstream=dict(type="str", default=""),
            upstream=dict(type="dict"),
            offline=dict(type="bool", default=False),
            docker_socket=dict(type="path", default="/var/run/docker.sock"),
        ),
        supports_check_mode=True,
    )
    p = module.params
    try:
        found = image_pin.pin_fleet(
            DockerSocket(p["docker_socket"], timeout=60),
            p["images"],
            p["configured"],
            p["registry_username"],
            p["registry_password"],
            p["asked_from"],
            p["mirror"],
            p["mirror_upstream"],
            upstream_answers=p["upstream"],
            offline=p["offline"],
        )
    except image_pin.PinError as exc:
        module.fail_json(msg=str(exc))
    module.exit_json(changed=False, **found)


if __name__ == "__main__":
    main()
