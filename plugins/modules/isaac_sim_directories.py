#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_directories
short_description: Create the persistent directories of Isaac Sim instances with one owner and mode
version_added: "0.1.0"
description:
  - Creates the missing directories and sets owner, group and mode in one pass, so a host with
    many instances (each with several cache, log and data directories) costs one task call.
  - Never removes anything; a path that exists and is not a directory fails the task untouched.
  - Supports check mode and diff.
author: isaacsim.fleet contributors (@isaacsim-fleet)
extends_documentation_fragment:
  - isaacsim.fleet.attributes
  - isaacsim.fleet.attributes.platform
attributes:
  check_mode:
    support: full
    details: Says which directories would be created or given their owner and mode; changes nothing.
  diff_mode:
    support: partial
    details: A line per directory changed - what it needed (create, owner, mode) and the owner, group and mode it
      gets; its earlier owner and mode are not shown.
  platform:
    platforms: posix
options:
  paths:
    description: Directories, parents first.
    type: list
    elements: path
    required: true
  owner:
    description: Numeric owner (the container user of the release, 1234 or 0).
    type: int
    required: true
  group:
    description: Numeric group.
    type: int
    required: true
  mode:
    description: Mode, as an octal string.
    type: str
    default: "0750"
"""

EXAMPLES = r"""
- name: Directories of instance 0 for Isaac Sim 5.x
  isaacsim.fleet.isaac_sim_directories:
    paths: [/var/lib/isaac-sim/instance-0, /var/lib/isaac-sim/instance-0/cache/main]
    owner: 1234
    group: 1234
"""

RETURN = r"""
changes:
  description: Each directory changed and why (create, owner, mode).
  returned: always
  type: list
  elements: list
  sample: [["/var/lib/isaac-sim/instance-0", "create"]]
"""

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import dirs


def main():
    module = AnsibleModule(
        argument_spec=dict(
            paths=dict(type="list", elements="path", required=True),
            owner=dict(type="int", required=True),
            group=dict(type="int", required=True),
            mode=dict(type="str", default="0750"),
        ),
        supports_check_mode=True,
    )
    p = module.params
    try:
        mode = int(p["mode"], 8)
    except ValueError:
        module.fail_json(msg=f"mode: {p['mode']!r} is not an octal mode such as 0750")
    changes = dirs.wanted_changes(p["paths"], p["owner"], p["group"], mode)
    if changes and not module.check_mode:
        try:
            dirs.apply(changes, p["owner"], p["group"], mode)
        except OSError as exc:
            module.fail_json(msg=str(exc), changes=changes)
    result = dict(changed=bool(changes), changes=changes)
    if module._diff and changes:
        result["diff"] = dict(
            before="".join(f"{path}: {what} needed\n" for path, what in changes),
            after="".join(f"{path}: directory {p['owner']}:{p['group']} {p['mode']}\n" for path, _what in changes),
        )
    module.exit_json(**result)


if __name__ == "__main__":
    main()
