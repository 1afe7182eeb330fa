"""The store of finished runs: what a run takes from controllers that went away, what retention
removes, and what it never touches (runs still going, runs waiting for their own controller)."""

import os
import shutil
import tarfile

from ansible_collections.isaacsim.fleet.plugins.module_utils.runs import run_store

NOW = 1_000_000.0
DAY = 86400


def entry(name, finished=None, mtime=None, fetched=False, taken=None, bundle=False):
    return {
        "name": name,
        "bundle": bundle,
        "mtime": mtime if mtime is not None else (finished if finished is not None else NOW),
        "finished": finished,
        "fetched": fetched,
        "taken": taken,
    }


def test_a_finished_run_waits_for_its_own_controller_then_is_taken():
    fresh = entry("fresh", finished=NOW - 30)
    left = entry("left", finished=NOW - 700)
    assert run_store.classify([fresh, left], set(), NOW, 600, 14 * DAY) == (["left"], [])


def test_a_taken_run_is_not_taken_again_until_its_taker_has_had_its_time():
    recent = entry("r", finished=NOW - 3000, taken=NOW - 60)
    stale = entry("s", finished=NOW - 3000, taken=NOW - 900)
    assert run_store.classify([recent, stale], set(), NOW, 600, 0) == (["s"], [])


def test_a_run_whose_runner_died_is_taken_at_once_but_only_once():
    swept = entry("swept", finished=NOW - 1)
    assert run_store.classify([swept], set(), NOW, 600, 0, ended={"swept"}) == (["swept"], [])
    again = entry("swept", finished=NOW - 1, taken=NOW - 1)
    assert run_store.classify([again], set(), NOW, 600, 0, ended={"swept"}) == ([], [])


def test_runs_going_on_fetched_runs_and_unfinished_ones_are_never_taken():
    live = entry("live", finished=None, mtime=NOW - 99 * DAY)
    fetched = entry("kept", finished=NOW - 3 * DAY, fetched=True)
    unfinished = entry("half", finished=None, mtime=NOW - 3 * DAY)
    assert run_store.classify([live, fetched, unfinished], {"live"}, NOW, 600, 14 * DAY) == ([], [])


def test_retention_removes_old_runs_fetched_or_not_and_zero_keeps_them_for_ever():
    old = [
        entry("a-old", finished=NOW - 15 * DAY),
        entry("b-kept-old", finished=NOW - 15 * DAY, fetched=True),
        entry("c-half-old", mtime=NOW - 15 * DAY),
    ]
    assert run_store.classify(old, set(), NOW, 600, 14 * DAY) == ([], ["a-old", "b-kept-old", "c-half-old"])
    assert run_store.classify(old, set(), NOW, 600, 0) == (["a-old"], [])


def test_bundles_nobody_fetched_go_once_their_controller_has_had_its_time():
    bundles = [
        entry("bundle-1.tar.gz", mtime=NOW - 10, bundle=True),
        entry("bundle-2.tar.gz", mtime=NOW - 601, bundle=True),
    ]
    assert run_store.classify(bundles, set(), NOW, 600, 0) == ([], ["bundle-2.tar.gz"])


def make_run(root, name, finished_at=None):
    d = root / name
    (d / "outputs").mkdir(parents=True)
    (d / "outputs" / "report.txt").write_text("ok\n")
    if finished_at is not None:
        (d / "result.json").write_text("{}\n")
        os.utime(d / "result.json", (finished_at, finished_at))
    return d


def remove(path):
    shutil.rmtree(path) if os.path.isdir(path) else os.remove(path)


def test_take_marks_what_it_takes_removes_what_expired_and_a_second_taker_gets_nothing(tmp_path):
    make_run(tmp_path, "left", finished_at=NOW - 700)
    make_run(tmp_path, "old", finished_at=NOW - 20 * DAY)
    make_run(tmp_path, "live")
    (tmp_path / "bundle-0.tar.gz").write_bytes(b"")
    os.utime(tmp_path / "bundle-0.tar.gz", (NOW - 700, NOW - 700))
    taken, removed = run_store.take(str(tmp_path), {"live"}, NOW, 600, 14, remove)
    assert taken == ["left"] and removed == ["bundle-0.tar.gz", "old"]
    assert sorted(p.name for p in tmp_path.iterdir()) == [".store.lock", "left", "live"]
    assert os.stat(tmp_path / "left" / run_store.TAKEN).st_mtime == NOW
    assert run_store.take(str(tmp_path), {"live"}, NOW + 1, 600, 14, remove) == ([], [])


def test_pack_carries_each_run_under_its_name_without_the_store_s_markers(tmp_path):
    make_run(tmp_path, "a", finished_at=NOW)
    make_run(tmp_path, "b", finished_at=NOW)
    (tmp_path / "a" / run_store.TAKEN).write_text("")
    path, packed = run_store.pack(str(tmp_path), ["a", "b", "gone"])
    assert packed == ["a", "b"] and os.path.dirname(path) == str(tmp_path)
    with tarfile.open(path) as tar:
        names = sorted(tar.getnames())
    assert "a/outputs/report.txt" in names and "b/result.json" in names
    assert not any(n.endswith(run_store.TAKEN) for n in names)
