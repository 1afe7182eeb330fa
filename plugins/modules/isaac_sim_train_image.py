#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_train_image
short_description: Turn the team's Docker image into what a Slurm cluster's jobs run, only when it changed
version_added: "0.4.0"
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

import os

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.train import slurm

# the program each runtime's build runs on the build host
_TOOL = {"apptainer": "apptainer", "enroot": "enroot", "podman": "docker", "docker": "docker"}


def main():
    module = AnsibleModule(
        argument_spec={
            "source": {"type": "str", "required": True},
            "runtime": {"type": "str", "required": True, "choices": list(slurm.RUNTIMES)},
            "build_dir": {"type": "path", "required": True},
            "present": {"type": "bool", "default": False},
            "fakeroot": {"type": "bool", "default": True},
        },
        supports_check_mode=True,
    )
    p = module.params
    docker = module.get_bin_path("docker")
    if not docker:
        module.fail_json(msg="train_image: the build host has no docker command. Fix: build where the image is.")
    rc, out, err = module.run_command([docker, "image", "inspect", "--format", "{{.Id}}", p["source"]])
    if rc != 0:
        module.fail_json(
            msg=f"train_image: {p['source']!r} is not an image of the build host's Docker ({err.strip()}). "
            "Fix: build or pull it there, or name one that `docker images` lists."
        )
    image_id = out.strip()
    name = slurm.image_file(p["source"], p["runtime"], image_id)
    done = {"id": image_id, "file": name, "path": os.path.join(p["build_dir"], name)}
    if p["present"]:
        module.exit_json(changed=False, built=False, **done)
    tool = module.get_bin_path(_TOOL[p["runtime"]])
    if not tool:
        module.fail_json(
            msg=f"train_runtime: {p['runtime']} images are built with {_TOOL[p['runtime']]}, which the build host "
            "lacks. Fix: install it there (Apptainer: https://apptainer.org/docs/admin/main/installation.html)."
        )
    # built beside the file and moved over it: a build that stops half way never stands as the image
    partial = done["path"] + ".partial"
    argv = slurm.build_argv(p["runtime"], p["source"], partial, fakeroot=p["fakeroot"])
    if module.check_mode:
        module.exit_json(changed=True, built=True, command=argv, **done)
    os.makedirs(p["build_dir"], exist_ok=True)
    if os.path.exists(partial):
        os.remove(partial)
    rc, out, err = module.run_command(argv)
    if rc != 0:
        module.fail_json(msg=f"{' '.join(argv)} failed ({rc}): {(err or out).strip()}", command=argv)
    os.replace(partial, done["path"])
    module.exit_json(changed=True, built=True, command=argv, **done)


if __name__ == "__main__":
    main()
