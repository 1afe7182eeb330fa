"""Every choice list of Isaac Sim releases (role argument specs, module documentation) and the URL
shapes of every release (plugins/module_utils/hostlib/endpoints.py) are the release table's
(plugins/module_utils/instance/releases.py): adding a release there and forgetting a list or its
URL shapes fails here, naming the list."""

import ast
from pathlib import Path

import yaml
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import endpoints
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import releases

ROOT = Path(__file__).resolve().parents[2]
# the release options without a choice list, and who refuses a release the table does not have
UNLISTED = {
    # the plan (instance/plan.py), naming the table's releases
    "roles/isaac_sim/meta/argument_specs.yml:main isaac_sim_release",
    "roles/isaac_sim/meta/argument_specs.yml:validate isaac_sim_release",
    "plugins/modules/isaac_sim_plan.py release",
    # the test run (runs/testrun.py); empty: the host's deployed release
    "roles/experience/meta/argument_specs.yml:main experience_simulator_release",
    "plugins/modules/isaac_sim_experience.py simulator_release",
}


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
    # the toolkit's, the nodes' (the role and its check), the training's, the driver check's
    assert sorted(where for where, _choices in found) == [
        "plugins/modules/nvidia_driver_check.py release",
        "roles/nvidia_container_toolkit/meta/argument_specs.yml:main nvidia_container_toolkit_release",
        "roles/slurm_node/meta/argument_specs.yml:check slurm_node_isaac_sim_release",
        "roles/slurm_node/meta/argument_specs.yml:main slurm_node_isaac_sim_release",
        "roles/train/meta/argument_specs.yml:main train_release",
    ]
    wrong = [f"{where}: {choices}" for where, choices in found if choices != list(releases.RELEASES)]
    assert wrong == [], f"not {list(releases.RELEASES)} (releases.RELEASES): {wrong}"


def test_every_release_option_has_the_table_s_choices_or_is_checked_against_the_table():
    unlisted = {where for where, name, spec in release_lists() if name.endswith("release") and not spec.get("choices")}
    assert unlisted == UNLISTED


def test_every_release_has_its_url_shapes_and_they_report_its_stream():
    assert list(endpoints.URLS) == list(releases.RELEASES)
    for name, release in releases.RELEASES.items():
        assert release["urls"] is endpoints.URLS[name]
        block = {kind: spec[1] for kind, spec in release["ports"].items()}
        # the default profile's stream (with its companions' ports, the 6.x web viewer's) is reported
        opens = release["profiles"][releases.STREAMING]["opens"]
        assert endpoints.endpoints(name, block, "h", served=block.values(), listens=opens), name
