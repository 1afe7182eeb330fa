"""The results directory's lock (the action plugin isaac_sim_results_lock) on real directories, as
playbooks/test_suite.yml holds it: this process's run, and other runs in processes forked from it
(a worker's parent is its ansible-playbook, so a child of this process is a run of its own whose
ansible-playbook is this process). Only the task and the connection are stand-ins."""

from __future__ import annotations

import getpass
import json
import os
import re
import socket
import traceback

import pytest
import yaml
from ansible.errors import AnsibleActionFail
from ansible_collections.isaacsim.fleet.plugins.action import isaac_sim_results_lock
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_results_lock as module
from ansible_collections.isaacsim.fleet.plugins.plugin_utils.run_hold import this_run

# the two tasks of playbooks/test_suite.yml, in its two plays
PLAN, REPORT = "Plan the suite, then run each host's share", "Report the suite"


class Task:
    """What an action plugin reads of its task."""

    action = "isaacsim.fleet.isaac_sim_results_lock"
    async_val = 0

    def __init__(self, args: dict, check_mode: bool):
        self.args, self.check_mode = args, check_mode


class Connection:
    """The controller's connection: the plugin never uses it."""

    class _shell:  # noqa: N801 - Ansible's attribute name
        tmpdir = None


def lock(args: dict, play: str = PLAN, check_mode: bool = False) -> dict:
    plugin = isaac_sim_results_lock.ActionModule(Task(args, check_mode), Connection(), None, None, None, None)
    plugin._load_name = Task.action  # as Ansible's plugin loader names it
    return plugin.run(task_vars={"ansible_play_name": play, "inventory_hostname": "gpu-1"})


def hold(directory, play: str = PLAN, **args) -> dict:
    """The playbook's first task: held by this run, test_suite_dir named in the errors."""
    return lock(dict({"path": str(directory), "variable": "test_suite_dir"}, **args), play)


def give_back(directory) -> dict:
    """The report play's last task."""
    return lock({"path": str(directory), "state": "absent"}, REPORT)


def in_another_run(act):
    """act()'s result, called in a forked process: a run of its own, whose ansible-playbook is this process."""
    read, write = os.pipe()
    pid = os.fork()
    if pid == 0:  # the other run: never back into pytest
        code = 1
        try:
            os.close(read)
            with os.fdopen(write, "w") as out:
                json.dump(act(), out)
            code = 0
        except BaseException:  # noqa: BLE001 - said on stderr, and by the exit code
            traceback.print_exc()
        finally:
            os._exit(code)
    os.close(write)
    with os.fdopen(read) as fh:
        text = fh.read()
    _pid, status = os.waitpid(pid, 0)
    assert os.waitstatus_to_exitcode(status) == 0, "the other run failed (its traceback is above)"
    return json.loads(text)


def holder(directory) -> dict:
    return json.loads((directory / ".suite-lock.json").read_text())


def test_a_missing_directory_is_made_and_held_by_this_run_until_it_gives_it_back(tmp_path):
    runs = tmp_path / "test-runs"
    assert hold(runs) == {"changed": False, "acquired": True, "note": ""}
    me = this_run(PLAN)
    found = holder(runs)
    assert runs.is_dir() and found["id"] == me["id"] and found["pid"] == os.getppid()
    assert (found["user"], found["controller"], found["play"]) == (getpass.getuser(), socket.gethostname(), PLAN)
    # the same run again (another play of it) holds it still, since it first took it
    assert hold(runs, play=REPORT)["acquired"] is True and holder(runs)["since"] == found["since"]
    assert give_back(runs) == {"changed": False, "released": True}
    assert not (runs / ".suite-lock.json").exists()
    assert give_back(runs)["released"] is False
    # a directory that never was: nothing to give back, and nothing is made
    assert give_back(tmp_path / "never")["released"] is False and not (tmp_path / "never").exists()


def test_a_second_suite_is_refused_naming_the_variable_and_the_holder_until_the_first_gives_it_back(tmp_path):
    runs = tmp_path / "test-runs"
    first = in_another_run(lambda: hold(runs))
    assert first["acquired"] is True
    taken = holder(runs)
    assert taken["pid"] == os.getpid() and taken["id"] != this_run(PLAN)["id"]

    refused = hold(runs)
    assert refused["failed"] is True and refused["holder"]["id"] == taken["id"]
    assert re.fullmatch(
        re.escape(
            f"test_suite_dir: {runs} is being written by another suite ({getpass.getuser()} on "
            f"{socket.gethostname()} (ansible-playbook pid {os.getpid()}, play {PLAN!r}) since "
        )
        + r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d UTC \(0 min ago\)"
        + re.escape(
            "); two suites there would overwrite each other's suite.json and junit.xml. Fix: give this one its "
            "own directory (-e test_suite_dir=...), or run it when that one has ended."
        ),
        refused["msg"],
    ), refused["msg"]
    # the refused suite gives back nothing of the other's, and the holder is untouched
    assert give_back(runs)["released"] is False and holder(runs) == taken

    assert in_another_run(lambda: give_back(runs))["released"] is True
    assert not (runs / ".suite-lock.json").exists()
    assert hold(runs)["acquired"] is True and holder(runs)["id"] == this_run(PLAN)["id"]
    # and now the other run is the one refused
    assert in_another_run(lambda: hold(runs))["failed"] is True


def test_a_suite_whose_ansible_playbook_is_gone_gives_the_directory_up_at_once(tmp_path):
    runs = tmp_path / "test-runs"
    # a run whose process ended without giving the directory back (killed, or its play failed)
    assert in_another_run(lambda: in_another_run(lambda: hold(runs)))["acquired"] is True
    gone = holder(runs)
    assert gone["pid"] not in (os.getpid(), os.getppid())

    taken = hold(runs)
    assert taken["acquired"] is True and holder(runs)["id"] == this_run(PLAN)["id"]
    assert taken["note"].startswith(
        f"took the lock left by {getpass.getuser()} on {socket.gethostname()} (ansible-playbook pid {gone['pid']}, "
    )
    assert taken["note"].endswith("that run has ended (its process is gone)")

    # an ended run of another controller sharing the directory cannot be told from a live one here
    (runs / ".suite-lock.json").write_text(json.dumps(dict(gone, controller="ctl-2", id="ctl-2:1:1")))
    refused = hold(runs)
    assert refused["failed"] is True and refused["holder"]["controller"] == "ctl-2"
    assert " on ctl-2 (ansible-playbook pid " in refused["msg"]


def test_check_mode_makes_no_directory(tmp_path):
    runs = tmp_path / "test-runs"
    assert lock({"path": str(runs)}, check_mode=True) == {"changed": False, "acquired": False}
    assert not runs.exists()


def test_an_empty_directory_is_an_error_naming_the_variable(tmp_path):
    assert hold("") == {"failed": True, "msg": "test_suite_dir is empty. Fix: give the results directory."}
    assert lock({"path": ""})["msg"] == "path is empty. Fix: give the results directory."


def test_the_options_are_checked_as_documented_so_a_misspelt_state_takes_nothing(tmp_path):
    runs = tmp_path / "test-runs"
    with pytest.raises(AnsibleActionFail) as refused:
        lock({"path": str(runs), "state": "released"})
    assert refused.value.message == "value of state must be one of: held, absent, got: released"
    with pytest.raises(AnsibleActionFail) as refused:
        lock({"path": str(runs), "wait": 600})
    assert refused.value.message == (
        "Unsupported parameters for (isaacsim.fleet.isaac_sim_results_lock) module: wait. "
        "Supported parameters include: path, state, variable."
    )
    with pytest.raises(AnsibleActionFail) as refused:
        lock({"state": "absent"})
    assert refused.value.message == "missing required arguments: path"
    assert not runs.exists()


def test_a_directory_under_home_is_the_one_the_suite_writes(tmp_path, monkeypatch):
    # the copy and fetch tasks that write the results expand ~ (their paths are of type path)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.chdir(tmp_path)
    assert hold("~/test-runs")["acquired"] is True
    assert holder(tmp_path / "home" / "test-runs")["id"] == this_run(PLAN)["id"]
    assert not (tmp_path / "~").exists()
    assert give_back("~/test-runs")["released"] is True


def test_it_checks_the_options_the_module_documents_and_returns_what_it_documents(tmp_path):
    doc = yaml.safe_load(module.DOCUMENTATION)
    documented = {
        name: {k: v for k, v in option.items() if k in ("type", "required", "choices", "default")}
        for name, option in doc["options"].items()
    }
    assert documented == isaac_sim_results_lock.ARGUMENT_SPEC
    assert sorted(yaml.safe_load(module.RETURN)) == ["acquired", "released"]
    held = lock({"path": str(tmp_path)})
    assert held["acquired"] is True and "released" not in held
    back = lock({"path": str(tmp_path), "state": "absent"})
    assert back["released"] is True and "acquired" not in back
