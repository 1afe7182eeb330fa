# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The summary printed by playbooks/rolling_restart.yml and upgrade.yml."""

from __future__ import annotations

DOCUMENTATION = r"""
name: isaac_sim_rollout_summary
short_description: What a rollout rolled, reverted and left untouched, and why it stopped
version_added: "0.2.0"
description:
  - "Takes C({host: isaac_sim_lifecycle result, or {} when not reached}) and the hosts of the rollout, and
    returns lines:
    instances rolled, already current, reverted (with the reason and where they are now), untouched
    (instances after a failure, hosts not reached), and why the rollout stopped, if it did."
positional: _input, targets, stopped_on
options:
  _input:
    description: "C({host: result}); none for a host the rollout did not reach."
    type: dict
    required: true
  targets:
    description: Every host of the rollout, in order.
    type: list
    elements: str
    required: true
  stopped_on:
    description: The host the rollout stopped on, or why it stopped, when no instance failed.
    type: str
"""

EXAMPLES = r"""
msg: "{{ outcomes | isaacsim.fleet.isaac_sim_rollout_summary(ansible_play_hosts_all) }}"
"""

RETURN = r"""
_value:
  description: Summary lines.
  type: list
  elements: str
"""


def isaac_sim_rollout_summary(*args, **kwargs):
    # on use, not at load: Ansible loads every filter file here to find one (docs/docsite/rst/contributing.rst, Layout)
    from ansible_collections.isaacsim.fleet.plugins.module_utils.instance.lifecycle import summary

    return summary(*args, **kwargs)


class FilterModule:
    def filters(self):
        return {"isaac_sim_rollout_summary": isaac_sim_rollout_summary}
