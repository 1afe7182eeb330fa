#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: docker_daemon_config
short_description: Merge settings into Docker's daemon.json
version_added: "0.1.0"
description:
  - Lays the given settings over the existing C(daemon.json). Nested objects are merged, other values
    replaced; keys not given are kept as they are.
  - Writes only when the merged content differs from the file's content, so formatting alone never
    causes a change (and never a Docker restart).
  - Refuses to touch a file that is not valid JSON.
  - Supports check mode and diff.
author: isaacsim.fleet contributors (@isaacsim-fleet)
options:
  path:
    description: The daemon.json file.
    type: path
    default: /etc/docker/daemon.json
  settings:
    description: Settings to merge in; none leaves the file as it is (and absent when it is absent).
    type: dict
    required: true
  restart_marker:
    description: A file that notes a Docker restart still to do; the module says whether it exists
      (RV(restart_noted)), so a role needs no second task to look.
    type: path
"""

EXAMPLES = r"""
- name: Wire the NVIDIA runtime into Docker
  isaacsim.fleet.docker_daemon_config:
    settings:
      runtimes:
        nvidia:
          path: nvidia-container-runtime
          args: []
  notify: Restart docker
"""

RETURN = r"""
config:
  description: The daemon configuration after the merge.
  returned: success
  type: dict
  sample: {"log-driver": "json-file", "runtimes": {"nvidia": {"path": "nvidia-container-runtime", "args": []}}}
restart_noted:
  description: Whether O(restart_marker) exists.
  returned: when O(restart_marker) is given
  type: bool
"""

import json
import os
import tempfile

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import daemon_json


def main():
    module = AnsibleModule(
        argument_spec=dict(
            path=dict(type="path", default="/etc/docker/daemon.json"),
            settings=dict(type="dict", required=True),
            restart_marker=dict(type="path"),
        ),
        supports_check_mode=True,
    )
    path = module.params["path"]
    text = None
    if os.path.exists(path):
        with open(path) as fh:
            text = fh.read()
    try:
        if module.params["settings"] or text is not None:
            changed, before, after = daemon_json.plan(text, module.params["settings"], path)
        else:  # nothing to merge into no file: no file is written
            changed, before, after = False, "", "{}"
    except daemon_json.DaemonJsonError as exc:
        module.fail_json(msg=str(exc))

    if changed and not module.check_mode:
        directory = os.path.dirname(path)
        os.makedirs(directory, mode=0o755, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=directory, prefix=".daemon.json.")
        with os.fdopen(fd, "w") as fh:
            fh.write(after)
        os.chmod(tmp, 0o644)
        module.atomic_move(tmp, path)

    result = dict(changed=changed, config=json.loads(after))
    if module.params["restart_marker"]:
        result["restart_noted"] = os.path.exists(module.params["restart_marker"])
    if module._diff:
        result["diff"] = dict(before=before, after=after, before_header=path, after_header=path)
    module.exit_json(**result)


if __name__ == "__main__":
    main()
