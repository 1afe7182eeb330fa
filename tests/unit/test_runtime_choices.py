"""What the roles keep of the Slurm runtimes is the runtime table's
(plugins/module_utils/train/runtimes.py): every choice list of runtimes (role argument specs,
module documentation), the slurm_node role's packages per runtime and the programs its node probe
looks for. Adding a runtime there and forgetting one of them fails here, naming it."""

import re
from pathlib import Path

import jinja2
import yaml
from ansible_collections.isaacsim.fleet.plugins.module_utils.train import runtimes
from ansible_collections.isaacsim.fleet.tests.unit.test_release_choices import release_lists

ROOT = Path(__file__).resolve().parents[2]
NODE = ROOT / "roles/slurm_node"
# the probe's programs that are not a runtime's
NOT_RUNTIMES = {"nvidia-smi", "nvidia-ctk", "slurmd"}


def test_every_runtime_choice_list_is_the_runtime_table():
    found = {
        where: [str(c) for c in spec["choices"]]
        for where, name, spec in release_lists()
        if name.endswith("runtime") and spec.get("choices")
    }
    assert sorted(found) == [
        "plugins/modules/isaac_sim_train_image.py runtime",
        "roles/slurm_node/meta/argument_specs.yml:check slurm_node_runtime",
        "roles/slurm_node/meta/argument_specs.yml:main slurm_node_runtime",
        "roles/train/meta/argument_specs.yml:main train_runtime",
    ]
    wrong = [f"{where}: {choices}" for where, choices in found.items() if choices != list(runtimes.RUNTIMES)]
    assert wrong == [], f"not {list(runtimes.RUNTIMES)} (runtimes.RUNTIMES): {wrong}"


def test_the_node_role_installs_each_runtime_s_packages():
    packages = yaml.safe_load((NODE / "vars/main.yml").read_text())["__slurm_node_runtime_packages"]
    assert sorted(packages) == sorted(runtimes.RUNTIMES)
    defaults = yaml.safe_load((NODE / "defaults/main.yml").read_text())
    env = jinja2.Environment()

    def rendered(listed, deb):
        given = {"slurm_node_apptainer_package": defaults["slurm_node_apptainer_package"]}
        return yaml.safe_load(env.from_string(str(listed)).render(__slurm_node_apptainer_deb=deb, **given))

    # apptainer's is the package slurm_node_apptainer_package names, by default the table's
    wrong = {
        name: listed
        for name, listed in packages.items()
        if rendered(listed, False) != runtimes.RUNTIMES[name]["node"]["packages"]
    }
    assert wrong == {}
    # and none when it names a .deb, which is installed by itself
    assert rendered(packages["apptainer"], True) == []


def test_the_node_probe_looks_for_each_runtime_s_program():
    probe = (NODE / "files/slurm-node-probe").read_text()
    programs = set(re.search(r"^for b in ([^;]+); do$", probe, re.MULTILINE).group(1).split())
    wanted = {entry["node"]["command"] for entry in runtimes.RUNTIMES.values()} - {None}
    assert programs - NOT_RUNTIMES == wanted
