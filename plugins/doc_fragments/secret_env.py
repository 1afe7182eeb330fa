# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

"""The names of the instances' secret variables, which the modules that take them (isaac_sim_plan,
isaac_sim_audit) are given without their values."""

from __future__ import annotations


class ModuleDocFragment:
    DOCUMENTATION = r"""
options:
  secret_env_names:
    description: The names of the instances' secret container variables (the keys of C(isaac_sim_secret_env));
      their values are never given to this module.
    type: list
    elements: str
    default: []
"""
