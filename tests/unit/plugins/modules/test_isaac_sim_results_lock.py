"""The module isaac_sim_results_lock is its documentation only: the action plugin of the same name
does the work on the controller (tests/unit/plugins/action/test_isaac_sim_results_lock_action.py
checks that it takes and returns what is documented here). What playbooks/test_suite.yml and the
examples pass it is documented, and the playbook gives back the directory it held."""

from __future__ import annotations

from pathlib import Path

import yaml
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_results_lock as module

ROOT = Path(__file__).resolve().parents[4]
NAME = "isaacsim.fleet.isaac_sim_results_lock"
DOC = yaml.safe_load(module.DOCUMENTATION)


def calls(tasks) -> list:
    """Every task of `tasks` (blocks and all) that calls the module."""
    found = []
    for task in tasks or []:
        if NAME in task:
            found.append(task)
        for key in ("block", "rescue", "always"):
            found += calls(task.get(key))
    return found


def test_it_documents_a_directory_held_or_given_back_and_the_variable_named_in_errors():
    assert DOC["module"] == "isaac_sim_results_lock"
    assert {name: (o["type"], o.get("required", False), o.get("default")) for name, o in DOC["options"].items()} == {
        "path": ("path", True, None),
        "state": ("str", False, "held"),
        "variable": ("str", False, "path"),
    }
    assert DOC["options"]["state"]["choices"] == ["held", "absent"]
    returned = yaml.safe_load(module.RETURN)
    assert {name: (r["type"], r["returned"]) for name, r in returned.items()} == {
        "acquired": ("bool", "when O(state=held)"),
        "released": ("bool", "when O(state=absent)"),
    }


def test_the_suite_playbook_holds_and_gives_back_one_directory_with_documented_options():
    plays = yaml.safe_load((ROOT / "playbooks" / "test_suite.yml").read_text())
    found = [(play["name"], play["vars"]["test_suite_dir"], t) for play in plays for t in calls(play.get("tasks"))]
    assert [(play, task[NAME]) for play, _dir, task in found] == [
        (
            "Plan the suite, then run each host's share",
            {"path": "{{ test_suite_dir }}", "variable": "test_suite_dir"},
        ),
        ("Report the suite", {"path": "{{ test_suite_dir }}", "state": "absent"}),
    ]
    # one directory in both plays: the one given back is the one held
    assert found[0][1] == found[1][1] == "{{ lookup('ansible.builtin.env', 'PWD') }}/test-runs"
    examples = yaml.safe_load(module.EXAMPLES)
    assert len(examples) == 1
    for task in [t for _play, _dir, t in found] + examples:
        args = task[NAME]
        assert set(args) <= set(DOC["options"]), args
        assert args.get("state", "held") in DOC["options"]["state"]["choices"]
