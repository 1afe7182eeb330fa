"""The day-2 actions are one table (instance/lifecycle_call.py DAY2): the lifecycle module's
action choices and the role's isaac_sim_action choices are its entries, so a new action added
there and forgotten in a list fails here, naming the list."""

import ast
from pathlib import Path

import yaml
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import lifecycle_call

ROOT = Path(__file__).resolve().parents[2]


def _module_documentation(path):
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Assign) and node.targets[0].id == "DOCUMENTATION":
            return yaml.safe_load(node.value.value)
    raise AssertionError(f"{path} has no DOCUMENTATION")


def test_the_module_documents_apply_and_every_day2_action():
    doc = _module_documentation(ROOT / "plugins/modules/isaac_sim_lifecycle.py")
    assert doc["options"]["action"]["choices"] == ["apply", *lifecycle_call.DAY2]


def test_the_role_offers_every_day2_action_and_no_other():
    specs = yaml.safe_load((ROOT / "roles/isaac_sim/meta/argument_specs.yml").read_text())["argument_specs"]
    listed = {
        entry: spec["options"]["isaac_sim_action"]["choices"]
        for entry, spec in specs.items()
        if "isaac_sim_action" in (spec.get("options") or {})
    }
    assert listed, "roles/isaac_sim/meta/argument_specs.yml: no entry has isaac_sim_action"
    for entry, choices in listed.items():
        assert choices == list(lifecycle_call.DAY2), f"roles/isaac_sim/meta/argument_specs.yml:{entry} isaac_sim_action"


def test_each_action_acts_through_the_lifecycle():
    """Every entry is a function of this module's, taking (host, params, out, found, check)."""
    for name, act in lifecycle_call.DAY2.items():
        assert act.__module__ == lifecycle_call.__name__, name
        assert act.__code__.co_varnames[:5] == ("host", "p", "out", "found", "check"), name
