"""The isaac_sim_mirror_seed module: what the storage lacks is copied, what it holds is left, check
mode copies nothing, and a copy that leaves a gap fails naming it."""

from __future__ import annotations

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import mirror_lock
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_mirror_seed
from ansible_collections.isaacsim.fleet.tests.unit.helpers import run_module

MIRROR = "10.0.0.9:5443"
HELD, NEW = "sha256:" + "aa" * 32, "sha256:" + "bb" * 32


@pytest.fixture(autouse=True)
def lock_file(monkeypatch, tmp_path):
    """The mirror's lock in the test's own directory, not the machine's /run/lock."""
    monkeypatch.setattr(mirror_lock, "LOCK", str(tmp_path / "mirror.lock"))
    return tmp_path / "mirror.lock"


@pytest.fixture()
def seeder(monkeypatch):
    state = {"copied": [], "holds": {("n/sim", HELD)}, "copy_works": True}

    class Seeder:
        def __init__(self, run):
            pass

        def lacking(self, images):
            return {image: [f"manifest {image[1]}"] for image in images if image not in state["holds"]}

        def copy(self, images, uid, gid, ready_timeout):
            state["copied"] += images
            if state["copy_works"]:
                state["holds"] |= set(images)

    class User:
        pw_uid, pw_gid = 104, 110

    monkeypatch.setattr(isaac_sim_mirror_seed.mirror_seed, "Seeder", Seeder)
    monkeypatch.setattr(isaac_sim_mirror_seed.pwd, "getpwnam", lambda name: User)
    return state


def args(**over):
    return {"references": [f"{MIRROR}/n/sim@{HELD}", f"{MIRROR}/n/sim@{NEW}"], "mirror": MIRROR, **over}


def test_what_the_mirror_lacks_is_copied_and_what_it_holds_is_left(seeder, capsys):
    result = run_module(isaac_sim_mirror_seed.main, args(), capsys)
    assert result["changed"] is True and seeder["copied"] == [("n/sim", NEW)]
    assert result["copied"] == [f"{MIRROR}/n/sim@{NEW}"] and result["held"] == [f"{MIRROR}/n/sim@{HELD}"]
    again = run_module(isaac_sim_mirror_seed.main, args(), capsys)
    assert again["changed"] is False and again["copied"] == [] and seeder["copied"] == [("n/sim", NEW)]


def test_check_mode_says_what_it_would_copy_and_copies_nothing(seeder, capsys):
    result = run_module(isaac_sim_mirror_seed.main, args(_ansible_check_mode=True), capsys)
    assert result["changed"] is True and result["copied"] == [f"{MIRROR}/n/sim@{NEW}"] and seeder["copied"] == []


def test_a_copy_that_leaves_a_gap_fails_naming_it(seeder, capsys):
    seeder["copy_works"] = False
    result = run_module(isaac_sim_mirror_seed.main, args(), capsys)
    assert result["failed"] and f"still lacks {MIRROR}/n/sim@{NEW}: manifest {NEW}" in result["msg"]


def test_a_reference_not_on_the_mirror_fails_before_any_copy(seeder, capsys):
    result = run_module(isaac_sim_mirror_seed.main, args(references=["nvcr.io/n/sim:6.0.1"]), capsys)
    assert result["failed"] and "is not an image pinned on the mirror" in result["msg"] and seeder["copied"] == []


def test_a_seed_waits_for_another_change_of_the_mirror_and_says_who_holds_it(seeder, lock_file, capsys):
    with mirror_lock.held("a garbage collection", 0):
        result = run_module(isaac_sim_mirror_seed.main, args(lock_timeout=0), capsys)
    assert result["failed"] and "the mirror is busy with a garbage collection (pid" in result["msg"]
    assert seeder["copied"] == []
    assert run_module(isaac_sim_mirror_seed.main, args(lock_timeout=0), capsys)["changed"] is True
