# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

"""The mirror's lock (module_utils/host/mirror_lock.py), held by every module that changes the registry
mirror's storage (isaac_sim_mirror_seed, isaac_sim_mirror_gc) for its whole time."""

from __future__ import annotations


class ModuleDocFragment:
    DOCUMENTATION = r"""
options:
  lock_timeout:
    description:
      - Seconds to wait while another run changes the mirror's storage (a seed of the pinned images, from this
        inventory or another, or a garbage collection); the mirror holds one such change at a time. After that the
        module fails, naming what holds the mirror, and changes nothing.
    type: int
    default: 3600
"""
