#!/usr/bin/python
# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

DOCUMENTATION = r"""
---
module: isaac_sim_results_lock
short_description: Hold a results directory on the controller for one suite at a time
version_added: "0.3.0"
description:
  - Runs on the controller only (an action plugin). Two suites writing one results directory would overwrite each
    other's C(suite.json), C(junit.xml) and bundles; the second is refused, naming the first.
  - The holder is this C(ansible-playbook) run, in C(PATH/.suite-lock.json); a holder whose process is gone (killed,
    failed before it gave the directory back) gives it up to the next suite at once.
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
    support: partial
    details: A directory that does not exist is not made and nothing is held; one that exists is taken (its lock file
      written) or given back as outside check mode, and refused while another suite writes there.
  diff_mode:
    support: none
    details: No diff is returned.
  platform:
    platforms: all
    details: Runs on the controller only; no host is contacted.
options:
  path:
    description: The results directory (made when missing).
    type: path
    required: true
  state:
    description: C(held) takes it, C(absent) gives it back (only when this run holds it).
    type: str
    choices: [held, absent]
    default: held
  variable:
    description: The variable the user sets the directory with, named in the error.
    type: str
    default: path
"""

EXAMPLES = r"""
- name: Hold the results directory for this suite
  isaacsim.fleet.isaac_sim_results_lock:
    path: "{{ test_suite_dir }}"
    variable: test_suite_dir
"""

RETURN = r"""
acquired:
  description: Whether this run holds the directory now.
  returned: when O(state=held)
  type: bool
released:
  description: Whether this run gave the directory back.
  returned: when O(state=absent)
  type: bool
"""
