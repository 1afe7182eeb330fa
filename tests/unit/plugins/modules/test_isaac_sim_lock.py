"""The isaac_sim_lock module end to end, its lock files in a temporary directory: taking,
refusing, renewing and giving back a host's lock, and check mode, which writes nothing."""

from __future__ import annotations

import json

import pytest
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_lock
from ansible_collections.isaacsim.fleet.tests.unit.helpers import ALICE, BOB, lock_files, run_module


@pytest.fixture()
def lock(tmp_path, monkeypatch):
    return lock_files(tmp_path / "run" / "lock", monkeypatch)


def test_a_free_host_is_taken_and_another_run_is_refused_with_who_holds_it(lock, capsys):
    taken = run_module(isaac_sim_lock.main, {"holder": ALICE}, capsys)
    assert taken["changed"] is False and taken["acquired"] is True and taken["note"] == ""
    assert taken["holder"]["id"] == ALICE["id"] and json.loads(lock.read_text())["id"] == ALICE["id"]
    refused = run_module(isaac_sim_lock.main, {"holder": BOB}, capsys)
    assert refused["acquired"] is False and refused["holder"]["id"] == ALICE["id"]
    assert refused["note"].startswith("alice on ctl-1 (ansible-playbook pid 100, play 'Deploy') since ")
    assert json.loads(lock.read_text())["id"] == ALICE["id"]
    broken = run_module(isaac_sim_lock.main, {"holder": BOB, "break_lock": True}, capsys)
    assert broken["acquired"] is True and broken["note"].startswith("took the lock from alice on ctl-1")


def test_check_mode_says_what_would_happen_and_writes_nothing(lock, capsys):
    checked = run_module(isaac_sim_lock.main, {"holder": ALICE, "_ansible_check_mode": True}, capsys)
    assert checked["acquired"] is True and checked["holder"] is None and not lock.exists()
    run_module(isaac_sim_lock.main, {"holder": ALICE}, capsys)
    held = run_module(isaac_sim_lock.main, {"holder": BOB, "_ansible_check_mode": True}, capsys)
    assert held["acquired"] is False and held["holder"]["id"] == ALICE["id"] and held["note"].startswith("alice")
    gone = run_module(isaac_sim_lock.main, {"holder": ALICE, "state": "absent", "_ansible_check_mode": True}, capsys)
    assert gone["released"] is False and lock.exists()


def test_only_the_holder_renews_and_gives_it_back(lock, capsys):
    run_module(isaac_sim_lock.main, {"holder": ALICE}, capsys)
    before = json.loads(lock.read_text())
    assert run_module(isaac_sim_lock.main, {"holder": BOB, "state": "renewed"}, capsys)["acquired"] is False
    assert run_module(isaac_sim_lock.main, {"holder": ALICE, "state": "renewed"}, capsys)["acquired"] is True
    after = json.loads(lock.read_text())
    assert after["since"] == before["since"] and after["renewed"] >= before["renewed"]
    assert run_module(isaac_sim_lock.main, {"holder": BOB, "state": "absent"}, capsys)["released"] is False
    back = run_module(isaac_sim_lock.main, {"holder": ALICE, "state": "absent"}, capsys)
    assert {k: back[k] for k in ("changed", "acquired", "released", "holder", "note")} == {
        "changed": False,
        "acquired": False,
        "released": True,
        "holder": None,
        "note": "",
    }
    assert not lock.exists()


def test_a_holder_without_an_id_and_an_unwritable_lock_are_errors_in_words(lock, capsys):
    result = run_module(isaac_sim_lock.main, {"holder": {"user": "alice"}}, capsys)
    assert result["msg"] == (
        "holder: needs an id. Fix: call isaacsim.fleet.isaac_sim_lock as a task (its action plugin fills it)."
    )
    lock.parent.parent.mkdir(parents=True)
    lock.parent.write_text("not a directory")
    result = run_module(isaac_sim_lock.main, {"holder": ALICE}, capsys)
    assert result["msg"].startswith(f"the lock {lock}: ")
