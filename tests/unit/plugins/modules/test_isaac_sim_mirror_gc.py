"""The isaac_sim_mirror_gc module: what is not kept is dropped, check mode drops nothing, a bad digest
is refused before anything."""

from __future__ import annotations

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import mirror_lock
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_mirror_gc
from ansible_collections.isaacsim.fleet.tests.unit.helpers import run_module

KEEP, DROP = "sha256:" + "aa" * 32, "sha256:" + "bb" * 32


@pytest.fixture(autouse=True)
def lock_file(monkeypatch, tmp_path):
    """The mirror's lock in the test's own directory, not the machine's /run/lock."""
    monkeypatch.setattr(mirror_lock, "LOCK", str(tmp_path / "mirror.lock"))
    return tmp_path / "mirror.lock"


@pytest.fixture()
def collector(monkeypatch):
    seen = {"collected": []}

    class Collector:
        def __init__(self, run):
            pass

        def plan(self, keep):
            return [("n/sim", d) for d in (KEEP, DROP) if d not in keep]

        def collect(self, images):
            seen["collected"] += images
            return 12345

    monkeypatch.setattr(isaac_sim_mirror_gc.mirror_gc, "Collector", Collector)
    return seen


def test_what_is_not_kept_is_dropped_and_the_bytes_freed_said(collector, capsys):
    result = run_module(isaac_sim_mirror_gc.main, {"keep": [KEEP]}, capsys)
    assert result["changed"] and result["dropped"] == [f"n/sim@{DROP}"] and result["freed_bytes"] == 12345
    assert collector["collected"] == [("n/sim", DROP)]
    nothing = run_module(isaac_sim_mirror_gc.main, {"keep": [KEEP, DROP]}, capsys)
    assert nothing["changed"] is False and nothing["dropped"] == []


def test_check_mode_says_what_it_would_drop_and_drops_nothing(collector, capsys):
    result = run_module(isaac_sim_mirror_gc.main, {"keep": [KEEP], "_ansible_check_mode": True}, capsys)
    assert result["changed"] and result["dropped"] == [f"n/sim@{DROP}"] and collector["collected"] == []


def test_a_keep_that_is_not_a_digest_is_refused_before_anything(collector, capsys):
    result = run_module(isaac_sim_mirror_gc.main, {"keep": ["nvcr.io/nvidia/isaac-sim:6.0.1"]}, capsys)
    assert result["failed"] and "keep: nvcr.io/nvidia/isaac-sim:6.0.1 not a digest" in result["msg"]
    assert collector["collected"] == []


def test_a_collection_waits_while_a_seed_runs_and_drops_nothing_meanwhile(collector, capsys):
    with mirror_lock.held("a seed of the pinned images", 0):
        result = run_module(isaac_sim_mirror_gc.main, {"keep": [KEEP], "lock_timeout": 0}, capsys)
    assert result["failed"] and "busy with a seed of the pinned images" in result["msg"]
    assert collector["collected"] == []
