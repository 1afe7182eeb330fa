#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.
# The work is done by the action plugin of the same name, on the controller.

DOCUMENTATION = r"""
---
module: isaac_sim_check_vars
short_description: Refuse variables of the wrong type before any role of the collection runs
version_added: "0.3.0"
description:
  - Checks every variable set for the given hosts (inventory, group and host vars, C(-e)) that a role of
    the collection declares in its C(meta/argument_specs.yml), against its type and choices.
  - A wrong type fails the task with one line per variable, its value, what it must be and the fix, and the
    hosts it was set for; Ansible's own validation at the role would print the whole spec for every host.
  - Runs on the controller only (an action plugin); playbooks/inventory_check.yml calls it first.
author: isaacsim.fleet contributors (@isaacsim-fleet)
extends_documentation_fragment:
  - isaacsim.fleet.attributes
  - isaacsim.fleet.attributes.platform
  - isaacsim.fleet.attributes.action
attributes:
  action:
    support: full
    details: The whole work is the action plugin's, on the controller; the module file holds only its
      documentation.
  check_mode:
    support: full
    details: Changes nothing; the same in check mode.
  diff_mode:
    support: none
    details: Nothing changes, so there is no diff.
  platform:
    platforms: all
    details: Runs on the controller only; no host is contacted.
options:
  hosts:
    description: The hosts whose variables are checked.
    type: list
    elements: str
    required: true
"""

EXAMPLES = r"""
- name: Refuse variables of the wrong type
  isaacsim.fleet.isaac_sim_check_vars:
    hosts: "{{ groups['isaac_sim_hosts'] }}"
"""

RETURN = r"""
msg:
  description: The variables refused, one line each.
  returned: failure
  type: str
"""
