# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

"""Options that name a place of the collection's host layout (module_utils/hostlib/layout.py), one text for
every module that takes them: a module extends isaacsim.fleet.layout.data_root or isaacsim.fleet.layout.config_dir
and does not document the option itself."""

from __future__ import annotations


class ModuleDocFragment:
    # nothing shared by every user of the layout: a module takes the options it has, by name (below)
    DOCUMENTATION = r"""
options: {}
"""

    DATA_ROOT = r"""
options:
  data_root:
    description:
      - The host's directory of the collection's data, the isaac_sim role's C(isaac_sim_data_root) - the instances'
        caches, logs and data (C(DATA_ROOT/instance-N)), the warmed caches (C(DATA_ROOT/warm-caches)), the Hub cache
        (C(DATA_ROOT/hub-cache)), the test runs (C(DATA_ROOT/runs/RUN)) and the dedicated simulators' caches
        (C(DATA_ROOT/simulators/N)).
      - The same directory for every module of the collection on a host.
    type: path
    default: /var/lib/isaac-sim
"""

    CONFIG_DIR = r"""
options:
  config_dir:
    description: Where the isaac_sim role writes the instances' env files (C(CONFIG_DIR/instance-N.env)).
    type: path
    default: /etc/isaac-sim
"""
