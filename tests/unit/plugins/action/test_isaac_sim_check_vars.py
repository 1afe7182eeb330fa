"""The inventory check's action plugin against the collection's real role argument specs: a
variable of the wrong type fails the task with one line naming it and the hosts it is set on."""

from __future__ import annotations

from unittest import mock

from ansible.errors import AnsibleUndefinedVariable
from ansible_collections.isaacsim.fleet.plugins.action import isaac_sim_check_vars


class HostVars(dict):
    """A host's variables; one whose template fails raises as Ansible's hostvars do."""

    def __getitem__(self, name):
        value = super().__getitem__(name)
        if value == "{{ undefined }}":
            raise AnsibleUndefinedVariable("'undefined' is undefined")
        return value


def check(hostvars: dict) -> dict:
    task = mock.MagicMock(async_val=0, check_mode=False)
    task.args = {"hosts": list(hostvars)}
    connection = mock.MagicMock()
    connection._shell.tmpdir = "/tmp/x"
    plugin = isaac_sim_check_vars.ActionModule(task, connection, mock.MagicMock(), None, None, None)
    return plugin.run(task_vars={"hostvars": {host: HostVars(v) for host, v in hostvars.items()}})


def test_right_types_pass_and_change_nothing():
    result = check({"gpu-1": {"isaac_sim_instance_count": 4, "isaac_sim_release": "6.x"}, "gpu-2": {}})
    assert result == {"changed": False}


def test_a_wrong_type_names_the_variable_and_the_hosts_it_is_set_on():
    result = check(
        {
            "gpu-1": {"isaac_sim_instance_count": "four"},
            "gpu-2": {"isaac_sim_instance_count": "four"},
            "gpu-3": {"isaac_sim_instance_count": 2, "isaac_sim_gpu_enabled": "perhaps"},
        }
    )
    assert result["failed"] and result["changed"] is False
    lines = result["msg"].splitlines()
    assert lines[0] == "Variables of the wrong type; nothing was changed on any host."
    [count] = [line for line in lines if "isaac_sim_instance_count" in line]
    [gpu] = [line for line in lines if "isaac_sim_gpu_enabled" in line]
    assert count.startswith("- ") and count.endswith("(hosts: gpu-1, gpu-2)") and "'four'" in count
    assert gpu.endswith("(hosts: gpu-3)")


def test_a_problem_on_every_host_says_so_and_a_failing_template_is_left_to_its_role():
    result = check(
        {
            "gpu-1": {"isaac_sim_gpu_enabled": "perhaps", "isaac_sim_instance_count": "{{ undefined }}"},
            "gpu-2": {"isaac_sim_gpu_enabled": "perhaps"},
        }
    )
    assert result["failed"] and len(result["msg"].splitlines()) == 2
    assert result["msg"].splitlines()[1].endswith("(every host)")
