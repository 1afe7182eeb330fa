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
  - With O(packages), also says which of them are not installed and, with O(service), the service's
    state, so a role learns what of Docker is on the host in the same call. While a package is missing
    the merge waits (nothing is written) and the role installs Docker and calls again.
  - Supports check mode and diff.
author: isaacsim.fleet contributors (@isaacsim-fleet)
extends_documentation_fragment:
  - isaacsim.fleet.attributes
  - isaacsim.fleet.attributes.platform
attributes:
  check_mode:
    support: full
    details: Merges in memory and says whether the file would change; writes nothing.
  diff_mode:
    support: full
    details: The file's content before and after the merge.
  platform:
    platforms: posix
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
  packages:
    description: Packages to look for with O(installed_query) (given together); while any is missing
      nothing is merged (RV(missing)).
    type: list
    elements: str
  installed_query:
    description: The package manager's query, run with O(packages) appended; it prints C(NAME ii) for
      each installed package, as C(dpkg-query --show) with the format C(${Package} ${db:Status-Abbrev}) does.
    type: list
    elements: str
  service:
    description: A systemd unit whose C(ActiveState) and C(UnitFileState) are returned (RV(service_state)).
    type: str
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
missing:
  description: The packages of O(packages) that are not installed; nothing was merged when any is.
  returned: always
  type: list
  elements: str
  sample: ["docker.io"]
service_state:
  description: The C(ActiveState) and C(UnitFileState) of O(service).
  returned: when O(service) is given
  type: dict
  sample: {"ActiveState": "active", "UnitFileState": "enabled"}
"""

import json
import os

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import daemon_json, docker_engine


def main():
    module = AnsibleModule(
        argument_spec=dict(
            path=dict(type="path", default="/etc/docker/daemon.json"),
            settings=dict(type="dict", required=True),
            restart_marker=dict(type="path"),
            packages=dict(type="list", elements="str"),
            installed_query=dict(type="list", elements="str"),
            service=dict(type="str"),
        ),
        # packages without the query that finds them would all read as missing, and nothing would merge
        required_together=[("packages", "installed_query")],
        supports_check_mode=True,
    )
    p = module.params
    found = docker_engine.probe(module.run_command, p["packages"] or [], p["installed_query"] or [], p["service"])
    if found["missing"]:
        module.exit_json(changed=False, config={}, **found, **_marker(p))
    try:
        changed, before, after = daemon_json.merge_file(p["path"], p["settings"], module.check_mode, module.atomic_move)
    except daemon_json.DaemonJsonError as exc:
        module.fail_json(msg=str(exc))
    result = dict(changed=changed, config=json.loads(after), **found, **_marker(p))
    if module._diff:
        result["diff"] = dict(before=before, after=after, before_header=p["path"], after_header=p["path"])
    module.exit_json(**result)


def _marker(p: dict) -> dict:
    return {"restart_noted": os.path.exists(p["restart_marker"])} if p["restart_marker"] else {}


if __name__ == "__main__":
    main()
