# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Why a training job stays COMPLETING, from the follow's result and the journal of its nodes."""

from __future__ import annotations

DOCUMENTATION = r"""
name: isaac_sim_train_stuck
short_description: Why a training job stays COMPLETING, naming its nodes and what their journal says
version_added: "0.3.0"
description:
  - Turns the failed result of M(isaacsim.fleet.isaac_sim_train_job) for a job stuck in C(COMPLETING) (its
    C(stuck_nodes)) and the journal read on each of those nodes into one message for a person, with the fix.
positional: _input, journals
options:
  _input:
    description: The module's failed result, with C(stuck_nodes), C(stuck_for) and C(node_states).
    type: dict
    required: true
  journals:
    description:
      - The results of C(journalctl -u slurmd -u munge) run on the nodes (a loop's C(results)), each with its
        C(item) (the node), C(stdout), C(stderr) and C(rc), or C(unreachable).
      - A node with no result is taken as not a host of the inventory.
    type: list
    elements: dict
    required: true
"""

EXAMPLES = r"""
msg: "{{ follow | isaacsim.fleet.isaac_sim_train_stuck(journal.results) }}"
"""

RETURN = r"""
_value:
  description: The message, ending with the fix.
  type: str
"""


def _read(result: dict) -> dict:
    """What one node's journal read gave: its text, or why it could not be read."""
    if result.get("unreachable"):
        return {"error": f"unreachable ({str(result.get('msg') or '').strip()})"}
    if result.get("rc") != 0:
        said = (result.get("stderr") or result.get("msg") or f"exit status {result.get('rc')}").strip()
        return {"error": said.splitlines()[-1] if said else f"exit status {result.get('rc')}"}
    return {"text": result.get("stdout") or ""}


def train_stuck(job: dict, journals: list) -> str:
    # on use, not at load: Ansible loads every filter file here to find one (docs/docsite/rst/contributing.rst, Layout)
    from ansible_collections.isaacsim.fleet.plugins.module_utils.train.slurm import stuck_message

    read = {str(r["item"]): _read(r) for r in journals or [] if "item" in r and not r.get("skipped")}
    return stuck_message(job, read)


class FilterModule:
    def filters(self):
        return {"isaac_sim_train_stuck": train_stuck}
