"""The facts playbooks/deploy.yml takes from its plan's call (module_utils/host/min_facts.py) against
ansible.builtin.setup's own with gather_subset [min], both collected here on this machine. (Here, not
under plugins/module_utils: ansible-test's module tests cannot import ansible.modules.)"""

from __future__ import annotations

from ansible.module_utils.basic import AnsibleModule
from ansible.modules import setup
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import min_facts
from ansible_collections.isaacsim.fleet.tests.unit.helpers import run_module

# the facts the collection's roles read (docker_engine, nvidia_container_toolkit, the package module)
READ = ("ansible_os_family", "ansible_distribution", "ansible_distribution_release", "ansible_architecture")
STEADY = READ + ("ansible_distribution_major_version", "ansible_pkg_mgr", "ansible_service_mgr", "ansible_python")


def _ours_min_facts():
    module = AnsibleModule(argument_spec={}, supports_check_mode=True)
    module.exit_json(ansible_facts=min_facts.collect(module))


def test_the_same_facts_as_setup_with_gather_subset_min(capsys):
    theirs = run_module(setup.main, {"gather_subset": ["min"]}, capsys)["ansible_facts"]
    ours = run_module(_ours_min_facts, {}, capsys)["ansible_facts"]
    assert set(ours) == set(theirs)
    assert all(ours[key] == theirs[key] for key in STEADY), [k for k in STEADY if ours[k] != theirs[k]]
    assert all(ours[key] for key in READ)
