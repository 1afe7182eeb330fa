"""The isaac_sim_train_stuck filter, as roles/train/tasks/stuck.yml calls it: the follow's failed
result | isaac_sim_train_stuck(the journal read on each node, a loop's results)."""

from __future__ import annotations

from ansible_collections.isaacsim.fleet.plugins.filter.isaac_sim_train_stuck import FilterModule

REFUSED = "2026-11-24T13:42:33+0000 node-2 slurmd[1615]: slurmd-node-2: error: Munge decode failed: Invalid credential"
JOB = {
    "id": "7",
    "state": "COMPLETING",
    "reason": "TimeLimit",
    "stuck_nodes": ["node-2", "node-3", "node-4", "gpu-9"],
    "stuck_for": 15,
    "node_states": {"node-2": {"state": "IDLE+COMPLETING+NOT_RESPONDING", "reason": ""}},
}


def test_each_node_is_named_with_what_its_journal_says_or_why_it_was_not_read():
    stuck = FilterModule().filters()["isaac_sim_train_stuck"]
    journals = [
        {"item": "node-2", "rc": 0, "stdout": REFUSED + "\n", "stderr": ""},
        # as a user outside the journal's groups
        {
            "item": "node-3",
            "rc": 1,
            "stdout": "",
            "stderr": "Hint: You are currently not seeing messages from other users and the system.\n"
            "No journal files were opened due to insufficient permissions.",
        },
        {"item": "node-4", "unreachable": True, "msg": "Failed to connect to the host via ssh: timed out"},
    ]
    text = stuck(JOB, journals)
    assert text.startswith(
        "job 7 has been COMPLETING for 15 s (Slurm's reason: TimeLimit): slurmctld waits for node-2 "
        "(IDLE+COMPLETING+NOT_RESPONDING), node-3, node-4, gpu-9 to end it"
    )
    assert f"node-2's journal (slurmd, munge): {REFUSED}." in text
    assert "node-3's journal could not be read: No journal files were opened due to insufficient permissions." in text
    assert "node-4's journal could not be read: unreachable (Failed to connect to the host via ssh: timed out)." in text
    # a Slurm node that is not a host of the inventory (the loop skipped it)
    assert "gpu-9 is not a host of the inventory: its journal was not read." in text
    assert "Fix: munge refuses credentials between node-2 and the controller" in text
