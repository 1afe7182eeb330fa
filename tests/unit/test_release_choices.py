"""Every choice list of Isaac Sim releases (role argument specs, module documentation) is the
release table's (plugins/module_utils/instance/releases.py): adding a release there and forgetting a list
fails here, naming the list."""

import ast
from pathlib import Path

import yaml
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import releases

ROOT = Path(__file__).resolve().parents[2]


def options(node, where):
    """(where, name, spec) for every option in an argument spec or module documentation, suboptions too."""
    for name, spec in (node or {}).items():
        if isinstance(spec, dict):
            yield f"{where} {name}", name, spec
            yield from options(spec.get("suboptions") or spec.get("options"), f"{where} {name}")


def release_lists():
    for path in sorted(ROOT.glob("roles/*/meta/argument_specs.yml")):
        specs = yaml.safe_load(path.read_text())["argument_specs"]
        for entry, spec in specs.items():
            yield from options(spec.get("options"), f"{path.relative_to(ROOT)}:{entry}")
    for path in sorted(ROOT.glob("plugins/modules/*.py")):
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.Assign) and getattr(node.targets[0], "id", "") == "DOCUMENTATION":
                doc = yaml.safe_load(node.value.value)
                yield from options(doc.get("options"), str(path.relative_to(ROOT)))


def test_every_release_choice_list_is_the_release_table():
    found = [
        (where, [str(c) for c in spec["choices"]])
        for where, name, spec in release_lists()
        if name.endswith("release") and spec.get("choices")
    ]
    assert len(found) >= 4, found  # the toolkit's, the driver check's, the nodes', the training's
    wrong = [f"{where}: {choices}" for where, choices in found if choices != list(releases.RELEASES)]
    assert wrong == [], f"not {list(releases.RELEASES)} (releases.RELEASES): {wrong}"
