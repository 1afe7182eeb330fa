# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
# Apache-2.0 is compatible with the GNU General Public License v3.0 that ansible-core is
# released under; ansible-test's validate-modules looks for that license's name here.

"""The host options of the modules that run experiences (isaac_sim_experience, isaac_sim_test_suite): one
argument spec for both, runner.HOST_OPTIONS in module_utils/runs/runner.py, and so one text. Their data_root
is isaacsim.fleet.layout.data_root."""

from __future__ import annotations


class ModuleDocFragment:
    DOCUMENTATION = r"""
options:
  gpus:
    description: The host's GPU ids that runs may give their services; each service that reserves GPUs gets ids of
      its own.
    type: list
    elements: str
    default: []
  unfetched_after:
    description:
      - Seconds a finished run's directory waits for the controller that started it; after that (its controller went
        away), the next run or suite on the host takes it and brings it back with its own (RV(recovered)). A run
        whose runner died is taken at once.
    type: float
    default: 600
  keep_days:
    description:
      - Days a run's directory (and a bundle nobody fetched) stays on the host at most, fetched or not
        (RV(expired)); C(0) keeps them for ever.
    type: float
    default: 14
  allowed_docker_args:
    description:
      - Arguments that take a service's container out of its confinement (C(privileged), C(cap_add), a
        C(security_opt) that turns a confinement off, C(pid)/C(ipc)/C(userns_mode) C(host), C(devices)) and that
        the operator allows all the same, each named exactly as docker run takes it (C(--cap-add=NET_ADMIN)).
      - A service that asks for one not named here is refused before anything starts.
    type: list
    elements: str
    default: []
"""
