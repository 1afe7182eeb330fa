"""The module isaac_sim_results_lock is its documentation only: the action plugin of the same name
does the work on the controller. What it documents is what the plugin takes and returns, and
what playbooks/test_suite.yml passes it."""

from __future__ import annotations

from pathlib import Path

import yaml
from ansible_collections.isaacsim.fleet.plugins.action import isaac_sim_results_lock as action
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_results_lock as module
from ansible_collections.isaacsim.fleet.tests.unit.plugins.action.test_isaac_sim_results_lock_action import lock

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


def test_the_documented_options_are_the_ones_the_action_plugin_checks():
    assert DOC["module"] == "isaac_sim_results_lock"
    documented = {
        name: {k: v for k, v in option.items() if k in ("type", "required", "choices", "default")}
        for name, option in DOC["options"].items()
    }
    assert documented == action.ARGUMENT_SPEC


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
    for task in [t for _play, _dir, t in found] + examples:
        args = task[NAME]
        assert set(args) <= set(DOC["options"]), args
        assert args.get("state", "held") in DOC["options"]["state"]["choices"]


def test_it_returns_what_it_documents(tmp_path):
    returned = yaml.safe_load(module.RETURN)
    assert sorted(returned) == ["acquired", "released"]
    held = lock({"path": str(tmp_path)})
    back = lock({"path": str(tmp_path), "state": "absent"})
    assert held["acquired"] is True and "released" not in held
    assert back["released"] is True and "acquired" not in back
    assert returned["acquired"]["returned"] == "when O(state=held)"
    assert returned["released"]["returned"] == "when O(state=absent)"
