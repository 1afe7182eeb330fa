"""Variables of the wrong type, refused in one line each against the roles' real argument specs."""

from pathlib import Path

import pytest
import yaml
from ansible_collections.isaacsim.fleet.plugins.module_utils.common import varcheck

ROLES = Path(__file__).resolve().parents[5] / "roles"
SPECS = varcheck.merged_specs(yaml.safe_load(p.read_text()) for p in sorted(ROLES.glob("*/meta/argument_specs.yml")))


@pytest.mark.parametrize(
    "name, value, said",
    [
        (
            "isaac_sim_instance_count",
            "four",
            "isaac_sim_instance_count: 'four' is not a whole number. Fix: give a "
            "whole number, such as -e isaac_sim_instance_count=",
        ),
        ("isaac_sim_rollout_soak", "abc", "isaac_sim_rollout_soak: 'abc' is not a number. Fix: give a number"),
        (
            "isaac_sim_env",
            [1],
            """isaac_sim_env: [1] is not a mapping. Fix: give a mapping, such as -e '{"isaac_sim_env": {}}'""",
        ),
        ("isaac_sim_rollout_mode", "sideways", "isaac_sim_rollout_mode: 'sideways' is not one of "),
        ("isaac_sim_accept_eula", "perhaps", "isaac_sim_accept_eula: 'perhaps' is not true or false."),
    ],
)
def test_a_wrong_type_is_one_line_with_the_value_and_the_fix(name, value, said):
    (problem,) = varcheck.problems(SPECS, {name: value})
    assert problem.startswith(said), problem
    assert "\n" not in problem and "_Ansible" not in problem


def test_values_typed_as_strings_on_the_command_line_pass_and_unknown_names_are_left_alone():
    values = {"isaac_sim_instance_count": "4", "isaac_sim_rollout_soak": "2.5", "isaac_sim_accept_eula": "yes"}
    assert varcheck.problems(SPECS, dict(values, someone_elses_variable=object())) == []


def test_a_variable_of_several_entry_points_takes_every_entry_points_choices():
    # rollout takes apply, rollout_preflight only restart and upgrade: apply is not refused here
    assert varcheck.problems(SPECS, {"isaac_sim_rollout_mode": "apply"}) == []
    assert "default" not in varcheck.want(SPECS["isaac_sim_rollout_mode"])
