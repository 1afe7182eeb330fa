#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_train_image
short_description: Turn the team's Docker image into what a Slurm cluster's jobs run, only when it changed
version_added: "0.3.0"
description:
  - Runs on the build host, where the team's image is in Docker. Reads the image's id (the digest of its
    configuration, which changes with any change of the image); the job image's file name carries it
    (C(NAME-ID12.sif)), so a new image never replaces the file a queued job is about to run.
  - Only when the cluster has no file for this id (O(present=false)) builds the job image in O(build_dir) and
    returns C(built=true); the caller copies it to the cluster.
  - Apptainer - a SIF with C(apptainer build); C(--fakeroot) lets a user without root build (user namespaces and
    C(/etc/subuid)), without it the build needs root. enroot - a squashfs image with C(enroot import). Podman and
    Docker - a C(docker save) archive that each node loads once.
author: isaacsim.fleet contributors (@isaacsim-fleet)
extends_documentation_fragment:
  - isaacsim.fleet.attributes
  - isaacsim.fleet.attributes.platform
attributes:
  check_mode:
    support: full
    details: Says whether a build is due and the command it would run; builds nothing.
  diff_mode:
    support: none
    details: No diff is returned.
  platform:
    platforms: posix
options:
  source:
    description: The team's image in the build host's Docker (name:tag or id).
    type: str
    required: true
  runtime:
    description: The cluster's job runtime.
    type: str
    required: true
    choices: [apptainer, podman, docker, enroot]
  build_dir:
    description: Where the job image is built, on the build host (one file per team image and runtime).
    type: path
    required: true
  present:
    description: Whether the cluster has the job image of this id already (the caller looks for C(file) there).
    type: bool
    default: false
  fakeroot:
    description: Build the SIF as a user with C(apptainer build --fakeroot); false builds as root.
    type: bool
    default: true
notes:
  - Check mode says whether a build is due and builds nothing.
"""

EXAMPLES = r"""
- name: Build the job image when the team's image changed
  isaacsim.fleet.isaac_sim_train_image:
    source: isaac-lab-base:latest
    runtime: apptainer
    build_dir: ~/.cache/isaacsim-fleet/train
    present: "{{ on_cluster.stat.exists }}"
"""

RETURN = r"""
id:
  description: The source image's id.
  returned: success
  type: str
  sample: sha256:0a45aaed62e1252814f088aebf8e435d91ce4f48e70df383fd5ea3fe634ad005
file:
  description: The job image's file name (the same on the cluster).
  returned: success
  type: str
  sample: isaac-lab-base_latest-0a45aaed62e1.sif
path:
  description: The job image on the build host.
  returned: success
  type: str
built:
  description: Whether the job image was built (the cluster's copy is out of date).
  returned: success
  type: bool
command:
  description: The build command run (or that would run).
  returned: when a build is due
  type: list
  elements: str
"""

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.train import job_image, runtimes


def main():
    module = AnsibleModule(
        argument_spec={
            "source": {"type": "str", "required": True},
            "runtime": {"type": "str", "required": True, "choices": list(runtimes.RUNTIMES)},
            "build_dir": {"type": "path", "required": True},
            "present": {"type": "bool", "default": False},
            "fakeroot": {"type": "bool", "default": True},
        },
        supports_check_mode=True,
    )
    p = module.params
    try:
        result = job_image.ensure(
            job_image.bind(module),
            p["source"],
            p["runtime"],
            p["build_dir"],
            present=p["present"],
            fakeroot=p["fakeroot"],
            check=module.check_mode,
        )
    except job_image.ImageError as exc:
        module.fail_json(msg=str(exc), **exc.result)
    module.exit_json(**result)


if __name__ == "__main__":
    main()
