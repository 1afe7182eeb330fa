"""The isaac_sim_door_token module on a real store: a token made once and kept, rotated, revoked and
listed; check mode writes nothing; a token asked for wrongly is refused naming the user's variable."""

from __future__ import annotations

import json

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.front import door_store
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_door_token
from ansible_collections.isaacsim.fleet.tests.unit.helpers import run_module


@pytest.fixture
def door(tmp_path):
    users = tmp_path / "users.json"
    users.write_text(json.dumps({"olga": {"role": "operator", "hash": "h"}, "vic": {"role": "viewer", "hash": "h"}}))
    return {"store": str(tmp_path / "door.db"), "users_file": str(users)}


def run(capsys, door, **args):
    return run_module(isaac_sim_door_token.main, dict(door, **args), capsys)


def test_a_token_is_made_once_kept_rotated_revoked_and_listed(capsys, door):
    made = run(capsys, door, user="olga", name="ci", scopes=["read", "act"], days=7)
    assert made["changed"] and made["token"].startswith("isf_") and made["record"]["scopes"] == ["read", "act"]
    store = door_store.Store(door["store"])
    assert store.token(made["token"])["user"] == "olga"
    kept = run(capsys, door, user="olga", name="ci", scopes=["read", "act"], days=7)
    assert not kept["changed"] and "token" not in kept and kept["record"]["id"] == made["record"]["id"]
    rotated = run(capsys, door, user="olga", name="ci", rotate=True)
    assert rotated["changed"] and store.token(made["token"]) is None and store.token(rotated["token"])
    gone = run(capsys, door, user="olga", name="ci", state="absent")
    assert gone["changed"] and gone["record"]["state"] == "revoked" and store.token(rotated["token"]) is None
    assert not run(capsys, door, user="olga", name="ci", state="absent")["changed"]
    listed = run(capsys, door, state="listed")
    assert not listed["changed"] and [t["state"] for t in listed["tokens"]] == ["revoked", "revoked"]
    assert all(set(t) == {"id", "user", "name", "scopes", "created", "expires", "state"} for t in listed["tokens"])


def test_check_mode_writes_nothing_and_returns_no_token(capsys, door):
    would = run(capsys, door, user="vic", name="look", _ansible_check_mode=True)
    assert would["changed"] and "token" not in would and would["tokens"] == []
    made = run(capsys, door, user="vic", name="look")
    revoke = run(capsys, door, user="vic", name="look", state="absent", _ansible_check_mode=True)
    assert revoke["changed"] and door_store.Store(door["store"]).token(made["token"])


def test_a_token_asked_for_wrongly_is_refused_naming_the_variable(capsys, door):
    failed = run(capsys, door, user="vic", name="ops", scopes=["read", "operate"], variable_prefix="front_door_token_")
    assert failed["failed"] and failed["msg"].startswith("front_door_token_scopes: vic is a viewer, who may hold read")
    failed = run(capsys, door, user="ann", name="x y", days=400, variable_prefix="front_door_token_")
    for said in (
        "front_door_token_name: 'x y' is not",
        "front_door_token_user: 'ann' is not",
        "front_door_token_days: 400",
    ):
        assert said in failed["msg"], failed["msg"]
    assert door_store.Store(door["store"]).tokens() == []


def test_a_front_door_not_set_up_is_named(capsys, tmp_path):
    nowhere = {"store": str(tmp_path / "door.db"), "users_file": str(tmp_path / "none.json")}
    failed = run(capsys, nowhere, state="listed")
    assert failed["failed"] and "Fix: run playbooks/front_door.yml first." in failed["msg"]
