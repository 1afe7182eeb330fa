"""The isaac_sim_layout filter, as roles/isaac_sim/vars/main.yml uses it: isaac_sim_data_root in, the
host's paths and unit names out, the same the plan hands the lifecycle module; every name the role
and the playbooks read from it exists, and the scripts it names are the role's files."""

from __future__ import annotations

import re

import pytest
import yaml
from ansible.errors import AnsibleUndefinedVariable
from ansible_collections.isaacsim.fleet.plugins.filter import isaac_sim_layout as plugin
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import plan
from ansible_collections.isaacsim.fleet.tests.unit.helpers import plan_config
from ansible_collections.isaacsim.fleet.tests.unit.plugins.filter.conftest import ROOT, load, trusted

HOST = {"memory_bytes": 64 * 1024**3, "gpu_count": 0, "ports_held": [], "image_present": True}


def role_vars(data_root: str) -> dict:
    """The role's variables (vars/main.yml) with isaac_sim_data_root set, as a play has them."""
    return dict(trusted(load("roles/isaac_sim/vars/main.yml")), isaac_sim_data_root=data_root)


def test_the_role_s_directories_and_file_paths_come_from_the_filter(render):
    variables = role_vars("/srv/isaac")
    dirs = render(
        "{{ [__isaac_sim_config_dir, __isaac_sim_unit_dir, __isaac_sim_libexec_dir, __isaac_sim_lib_dir,"
        " __isaac_sim_run_dir] }}",
        variables,
    )
    assert dirs == [
        "/etc/isaac-sim",
        "/etc/systemd/system",
        "/usr/local/libexec/isaac-sim",
        "/usr/local/lib/isaac-sim/status",
        "/run/isaac-sim",
    ]
    assert render("{{ __isaac_sim_status_paths }}", variables) == [
        "/etc/systemd/system/isaac-sim-status.service",
        "/usr/local/libexec/isaac-sim/isaac-sim-status-server",
        "/etc/isaac-sim/status.env",
    ]
    assert render("{{ __isaac_sim_metrics_paths }}", variables) == [
        "/etc/systemd/system/isaac-sim-metrics.service",
        "/etc/systemd/system/isaac-sim-metrics.timer",
        "/usr/local/libexec/isaac-sim/isaac-sim-metrics",
    ]
    # the data root is the inventory's; only it and the Hub cache's default directory move with it
    assert render("{{ [__isaac_sim_layout.data_root, __isaac_sim_layout.hub_dir] }}", variables) == [
        "/srv/isaac",
        "/srv/isaac/hub-cache",
    ]


def test_every_name_the_role_and_playbooks_read_is_there_and_names_the_role_s_scripts():
    used = set()
    for path in [*ROOT.glob("roles/*/**/*.yml"), *ROOT.glob("playbooks/*.yml")]:
        used |= set(re.findall(r"__isaac_sim_layout\.(\w+)", path.read_text()))
    given = plugin.isaac_sim_layout("/var/lib/isaac-sim")
    assert {"target", "unit_template", "status_unit", "metrics_timer", "hub_dropin"} <= used
    assert sorted(used - set(given)) == []
    # the documented names too
    documented = yaml.safe_load(plugin.RETURN)["_value"]["description"]
    assert sorted(set(re.findall(r"C\((\w+)\)", documented)) - set(given)) == []
    # the role looks the scripts up by these names in its files/
    for script in ("status_script", "metrics_script"):
        assert (ROOT / "roles" / "isaac_sim" / "files" / given[script]).is_file(), given[script]


@pytest.mark.parametrize("data_root", ["/var/lib/isaac-sim", "/srv/isaac"])
def test_the_filter_gives_the_layout_the_plan_gives_the_lifecycle_module(data_root):
    planned = plan.build(plan_config(data_root=data_root), HOST)
    assert plugin.FilterModule().filters()["isaac_sim_layout"](data_root) == planned["layout"]


def test_the_filter_passes_the_data_root_on_as_given_and_the_plan_refuses_a_wrong_one():
    # validate.yml plans with the same isaac_sim_data_root: the error names it there
    assert plugin.isaac_sim_layout("srv/isaac")["data_root"] == "srv/isaac"
    with pytest.raises(plan.PlanError) as refused:
        plan.build(plan_config(data_root="srv/isaac"), HOST)
    assert refused.value.errors == [
        "isaac_sim_data_root: 'srv/isaac' must be an absolute path without spaces or colons. "
        "Fix: use e.g. /var/lib/isaac-sim."
    ]


def test_an_undefined_data_root_names_the_variable(render):
    variables = role_vars("/srv/isaac")
    del variables["isaac_sim_data_root"]
    with pytest.raises(AnsibleUndefinedVariable, match="'isaac_sim_data_root' is undefined"):
        render("{{ __isaac_sim_unit_dir }}", variables)
