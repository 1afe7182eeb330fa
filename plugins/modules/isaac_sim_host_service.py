#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_host_service
short_description: Bring one of the collection's host services (files and systemd unit) to a state in one call
version_added: "0.3.0"
description:
  - For the services of a host that are not Isaac Sim instances, such as the read-only status endpoint
    (C(isaac-sim-status.service)). Instances change only through M(isaacsim.fleet.isaac_sim_lifecycle).
  - O(state=started) writes the files whose content or mode differ (atomically), reloads systemd when a unit
    file changed, enables the unit, starts it, and restarts it when one of its files changed while it ran.
  - O(state=absent) stops and disables the unit, then removes its files and O(remove).
  - One call per service and run, whatever the number of files; supports check mode and diff.
author: isaacsim.fleet contributors (@isaacsim-fleet)
extends_documentation_fragment:
  - isaacsim.fleet.attributes
  - isaacsim.fleet.attributes.platform
attributes:
  check_mode:
    support: full
    details: Says which files would be written or removed and what would be done to the unit; changes nothing.
  diff_mode:
    support: partial
    details: Names the files that are (or would be) written or removed; their content is not shown.
  platform:
    platforms: posix
options:
  name:
    description: The systemd unit, e.g. C(isaac-sim-status.service).
    type: str
    required: true
  files:
    description:
      - Path to C(content) and C(mode) (octal string, default C(0644)) of each file of the service, the unit
        file among them; C(uid) and C(gid) (numbers) for a file the service reads as its own user (default root's).
    type: dict
    default: {}
  directories:
    description:
      - Directories the service needs before it starts - C(path), C(uid), C(gid), C(mode) (octal string). Created
        when missing and re-owned when owned otherwise; never emptied, and kept with O(state=absent).
    type: list
    elements: dict
    default: []
  remove:
    description: Further paths (files or directories) to remove with O(state=absent).
    type: list
    elements: path
    default: []
  state:
    description: Whether the service runs (C(started)) or is gone (C(absent)).
    type: str
    choices: [started, absent]
    default: started
"""

EXAMPLES = r"""
- name: Serve this host's status
  isaacsim.fleet.isaac_sim_host_service:
    name: isaac-sim-status.service
    files:
      /etc/systemd/system/isaac-sim-status.service:
        content: "{{ lookup('ansible.builtin.template', 'isaac-sim-status.service.j2') }}"
      /usr/local/libexec/isaac-sim/isaac-sim-status-server:
        content: "{{ lookup('ansible.builtin.file', 'isaac-sim-status-server') }}"
        mode: "0755"
"""

RETURN = r"""
changed_files:
  description: The files written or removed.
  returned: always
  type: list
  elements: str
actions:
  description: What was done, in order (directories, write, daemon-reload, enable, start, restart, stop, disable,
    remove).
  returned: always
  type: list
  elements: str
"""

from ansible.module_utils.basic import AnsibleModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import host_service


def main():
    module = AnsibleModule(
        argument_spec=dict(
            name=dict(type="str", required=True),
            files=dict(type="dict", default={}),
            directories=dict(type="list", elements="dict", default=[]),
            remove=dict(type="list", elements="path", default=[]),
            state=dict(type="str", choices=["started", "absent"], default="started"),
        ),
        supports_check_mode=True,
    )
    try:
        service = host_service.Service(
            module.params, module.get_bin_path("systemctl", required=True), module.run_command
        )
        module.exit_json(**service.apply(module.check_mode))
    except host_service.ServiceError as e:
        module.fail_json(msg=e.msg, **e.details)


if __name__ == "__main__":
    main()
