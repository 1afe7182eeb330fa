"""The host's run lock against real files: two runs never both hold it, a run renews its own,
an ended or stale run's lock is taken over and says from whom."""

import json
import multiprocessing
import os
import subprocess

from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import runlock

ALICE = {"id": "ctl-1:100:5", "user": "alice", "controller": "ctl-1", "pid": 100, "started": "5", "play": "Deploy"}
BOB = {"id": "ctl-2:200:7", "user": "bob", "controller": "ctl-2", "pid": 200, "started": "7", "play": "Deploy"}
NOW = 1795000000.0


def paths(tmp_path):
    return {"path": str(tmp_path / "run" / "lock.json"), "guard": str(tmp_path / "run" / ".guard")}


def recorded(tmp_path):
    return str(tmp_path / "run" / "rollout.json")


def test_a_free_host_is_taken_and_another_run_is_refused_naming_who_and_since_when(tmp_path):
    where = paths(tmp_path)
    assert runlock.acquire(ALICE, NOW, 3600, **where)[0]
    acquired, holder, who = runlock.acquire(BOB, NOW + 125, 3600, **where)
    assert not acquired and holder["id"] == ALICE["id"]
    assert who.startswith("alice on ctl-1 (ansible-playbook pid 100, play 'Deploy') since ")
    assert who.endswith("(2 min ago)")


def test_a_run_renews_its_own_lock_and_keeps_its_start(tmp_path):
    where = paths(tmp_path)
    runlock.acquire(ALICE, NOW, 3600, **where)
    acquired, holder, note = runlock.acquire(ALICE, NOW + 3000, 3600, **where)
    assert acquired and note == "" and holder["since"] == NOW and holder["renewed"] == NOW + 3000
    # renewed: still held an hour after it was first taken
    assert not runlock.acquire(BOB, NOW + 3700, 3600, **where)[0]


def test_a_lock_not_renewed_for_stale_after_is_taken_over(tmp_path):
    where = paths(tmp_path)
    runlock.acquire(ALICE, NOW, 3600, **where)
    acquired, holder, note = runlock.acquire(BOB, NOW + 3600, 3600, **where)
    assert acquired and holder["id"] == BOB["id"]
    assert note.startswith("took the lock from alice on ctl-1") and "not renewed for 3600 s" in note


def test_an_ended_run_or_an_operator_breaking_it_takes_it_at_once(tmp_path):
    where = paths(tmp_path)
    runlock.acquire(ALICE, NOW, 3600, **where)
    # the controller found another holder dead: no takeover
    assert not runlock.acquire(BOB, NOW + 1, 3600, dead="ctl-9:1:1", **where)[0]
    acquired, _holder, note = runlock.acquire(BOB, NOW + 1, 3600, dead=ALICE["id"], **where)
    assert acquired and "that run has ended" in note
    acquired, _holder, note = runlock.acquire(ALICE, NOW + 2, 0, break_lock=True, **where)
    assert acquired and "isaac_sim_lock_break" in note and "bob on ctl-2" in note


def test_release_frees_only_the_holders_lock(tmp_path):
    where = paths(tmp_path)
    runlock.acquire(ALICE, NOW, 3600, **where)
    assert not runlock.release(BOB, **where)
    assert os.path.exists(where["path"])
    assert runlock.release(ALICE, **where)
    assert runlock.read(where["path"]) is None and not runlock.release(ALICE, **where)


def test_an_unreadable_lock_file_is_replaced(tmp_path):
    where = paths(tmp_path)
    os.makedirs(os.path.dirname(where["path"]))
    with open(where["path"], "w") as fh:
        fh.write("{half")
    acquired, holder, note = runlock.acquire(BOB, NOW, 3600, **where)
    assert acquired and holder["user"] == "bob" and "unreadable" in note
    with open(where["path"]) as fh:
        assert json.load(fh)["id"] == BOB["id"]


def _race(where, n, start, out):
    me = {"id": f"ctl:{n}:1", "user": f"u{n}", "controller": "ctl", "pid": n, "started": "1", "play": ""}
    start.wait()
    out.put(runlock.acquire(me, NOW, 3600, **where)[0])


def test_runs_that_find_the_host_free_at_the_same_moment_never_both_take_it(tmp_path):
    where = paths(tmp_path)
    ctx = multiprocessing.get_context("fork")
    start, out = ctx.Event(), ctx.Queue()
    procs = [ctx.Process(target=_race, args=(where, n, start, out)) for n in range(8)]
    for p in procs:
        p.start()
    start.set()
    for p in procs:
        p.join(10)
    assert sorted(out.get(timeout=5) for _proc in procs) == [False] * 7 + [True]


def test_the_heartbeat_renews_only_the_holders_lock_and_a_silent_holder_is_gone(tmp_path):
    where = paths(tmp_path)
    assert not runlock.renew(ALICE, NOW, **where)
    runlock.acquire(ALICE, NOW, 3600, **where)
    assert not runlock.renew(BOB, NOW + 10, **where)
    assert runlock.renew(ALICE, NOW + 40, **where) and runlock.read(where["path"])["since"] == NOW
    assert runlock.gone(ALICE["id"], NOW + 80, 45, where["path"]) == ""
    assert runlock.HEARTBEAT_LIMIT_S == 30
    assert "stopped renewing its hold on the host 46 s ago" in runlock.gone(ALICE["id"], NOW + 86, 45, where["path"])
    runlock.acquire(BOB, NOW + 90, 3600, break_lock=True, **where)
    assert runlock.gone(ALICE["id"], NOW + 91, 45, where["path"]).startswith("the host's lock was taken by bob")
    os.unlink(where["path"])
    assert "given back" in runlock.gone(ALICE["id"], NOW + 92, 45, where["path"])


def test_the_run_that_takes_over_an_interrupted_runs_lock_is_told_what_it_left(tmp_path):
    where = paths(tmp_path)
    runlock.acquire(ALICE, NOW, 3600, **where)
    entry = {
        "run": ALICE["id"],
        "at": NOW + 5,
        "interrupted": "its controller stopped",
        "done": [0],
        "untouched": [2, 3],
    }
    runlock.record(entry, recorded(tmp_path))
    acquired, _holder, note = runlock.acquire(
        BOB, NOW + 60, 3600, dead=ALICE["id"], record_path=recorded(tmp_path), **where
    )
    assert acquired and "that run has ended" in note
    assert "interrupted (its controller stopped): done isaac-sim-0; left as they were isaac-sim-2, isaac-sim-3" in note
    # a record of another run says nothing
    assert runlock.recorded_text(entry, BOB["id"]) == ""


def test_request_is_the_module_s_call_on_the_files_it_is_given(tmp_path):
    where = dict(paths(tmp_path), record_path=recorded(tmp_path))
    params = {"holder": ALICE, "state": "present", "stale_after": 3600, "break_lock": False, "dead": ""}
    assert runlock.request(params, NOW, check=True, **where) == {
        "acquired": True,
        "holder": None,
        "note": "",
        "job_running": False,
    }
    assert not os.path.exists(where["path"])
    taken = runlock.request(params, NOW, **where)
    assert taken["acquired"] and taken["holder"]["since"] == NOW
    assert runlock.request(dict(params, state="renewed"), NOW + 5, **where)["acquired"]
    assert runlock.read(where["path"])["renewed"] == NOW + 5
    assert runlock.request(dict(params, state="absent"), NOW, **where)["released"]
    try:
        runlock.request(dict(params, holder={}), NOW, **where)
    except runlock.LockError as exc:
        assert str(exc).startswith("holder: needs an id.")
    else:
        raise AssertionError("a holder without an id was accepted")


def test_an_ended_run_is_taken_over_only_once_its_lifecycle_job_here_has_ended(tmp_path):
    """A killed ansible-playbook's background job may still be restarting an instance on the host: the
    next run waits for it (job_running) however it would take over (ended, isaac_sim_lock_break, stale)."""
    where = paths(tmp_path)
    params = {"holder": ALICE, "state": "present", "stale_after": 3600, "break_lock": False, "dead": ""}
    assert runlock.request(params, NOW, **where)["acquired"]
    job = subprocess.Popen(["sleep", "30"])
    try:
        assert runlock.mark_job(ALICE["id"], job.pid, path=where["path"])
        # the controller's renewals and its own re-take keep the job recorded
        assert runlock.request(dict(params, state="renewed"), NOW + 5, **where)["acquired"]
        assert runlock.request(params, NOW + 6, **where)["acquired"]
        assert runlock.read(where["path"])["job"]["pid"] == job.pid
        bob = dict(params, holder=BOB)
        for how in ({"dead": ALICE["id"]}, {"stale_after": 1}):
            answer = runlock.request(dict(bob, **how), NOW + 60, **where)
            assert answer["acquired"] is False and answer["job_running"] is True, how
            assert f"its lifecycle job still runs on this host (pid {job.pid})" in answer["note"]
            assert runlock.read(where["path"])["id"] == ALICE["id"]
        # a run that holds it (not ended) is just held, as before
        held = runlock.request(bob, NOW + 60, **where)
        assert held["acquired"] is False and held["job_running"] is False
        # the operator's break is the escape from a job that hangs: taken at once
        broken = runlock.request(dict(bob, break_lock=True), NOW + 60, **where)
        assert broken["acquired"] is True and "(isaac_sim_lock_break)" in broken["note"]
        runlock.request(dict(params, break_lock=True), NOW + 61, **where)
        runlock.mark_job(ALICE["id"], job.pid, path=where["path"])
    finally:
        job.kill()
        job.wait()
    # the job ended (killed, or done): the ended run is taken over
    answer = runlock.request(dict(params, holder=BOB, dead=ALICE["id"]), NOW + 90, **where)
    assert answer["acquired"] is True and "took the lock left by" in answer["note"]


def test_a_job_record_whose_pid_now_names_another_process_is_no_job(tmp_path):
    where = paths(tmp_path)
    params = {"holder": ALICE, "state": "present", "stale_after": 3600, "break_lock": False, "dead": ""}
    runlock.request(params, NOW, **where)
    assert runlock.mark_job(ALICE["id"], os.getpid(), path=where["path"])
    current = runlock.read(where["path"])
    assert runlock.job_running(current) == f"pid {os.getpid()}"
    # the same pid, another start time: a process that reused the job's pid
    assert runlock.job_running(dict(current, job=dict(current["job"], started="1"))) == ""
    runlock.clear_job(ALICE["id"], os.getpid(), path=where["path"])
    assert "job" not in runlock.read(where["path"])
    # only the holder's own job is recorded
    assert runlock.mark_job(BOB["id"], os.getpid(), path=where["path"]) is False


def test_two_threads_of_one_process_write_the_lock_each_whole(tmp_path):
    """An agent's renewer and its lifecycle call write the lock from one process: each write is whole
    (a temporary file of its own thread), so neither ever fails for the other's rename."""
    import threading

    path = str(tmp_path / "lock.json")
    failures = []

    def writer(n):
        for i in range(300):
            try:
                runlock._write(path, {"id": f"w{n}", "i": i})
            except OSError as exc:
                failures.append(exc)

    threads = [threading.Thread(target=writer, args=(n,)) for n in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert failures == [] and runlock.read(path)["id"].startswith("w")
