# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

"""The attributes every module of the collection declares (tests/unit/test_module_docs.py holds each module
to them): a module extends isaacsim.fleet.attributes and gives check_mode and diff_mode their support,
isaacsim.fleet.attributes.platform and gives platform its platforms, and, where an action plugin of the
same name runs on the controller, isaacsim.fleet.attributes.action. The descriptions are here; each module
says only its support and its details."""

from __future__ import annotations


class ModuleDocFragment:
    DOCUMENTATION = r"""
options: {}
attributes:
  check_mode:
    description: Can run in check mode (C(--check)) and say whether it would change the target, without changing it.
  diff_mode:
    description: Returns what it changed (in check mode, what it would change) when run in diff mode (C(--diff)).
"""

    PLATFORM = r"""
options: {}
attributes:
  platform:
    description: Target OS/families that can be operated against.
    support: N/A
"""

    ACTION = r"""
options: {}
attributes:
  action:
    description: Has an action plugin of the same name, so part of its work is done on the controller.
"""
