"""The host's action agent (module_utils/instance/agent.py): requests checked field by field, the
N-1 rule, the host's lock shared with playbook runs, the action's events and outcome kept on
disk, and the channel that answers the front door's certificate alone (real TLS on a real socket,
certificates made with openssl)."""

from __future__ import annotations

import http.client
import io
import json
import os
import socket
import ssl
import subprocess
import tarfile
import threading
import time
from pathlib import Path

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import agent, lifecycle, runlock
from ansible_collections.isaacsim.fleet.tests.unit.helpers import make_pki
from ansible_collections.isaacsim.fleet.tests.unit.plugins.module_utils.instance.test_lifecycle import (
    ScriptedHost,
    documents,
    real_files,
)


def make(tmp_path, n=4, running=True, **over):
    """An agent over a scripted host of n instances; its lock, record and state in tmp_path."""
    h = ScriptedHost(n, running=running)
    h.host.wall = time.time
    lines = []
    a = agent.Agent(
        "gpu-1",
        str(tmp_path / "state"),
        host=lambda: h.host,
        lock=str(tmp_path / "lock.json"),
        record=str(tmp_path / "record.json"),
        drained=str(tmp_path / "drained.json"),
        journal=lambda line, unit="": lines.append((unit, line)),
        renew_s=0.05,
        **over,
    )
    return a, h, lines


def req(action="restart", ids=(2,), **over) -> dict:
    body = {"host": "gpu-1", "action": action, "ids": list(ids), "user": "alice"}
    body.update(over)
    return agent.parse_request(json.dumps(body).encode())


@pytest.mark.parametrize(
    ("body", "code", "words"),
    [
        (b"[1]", 400, "not a JSON object"),
        (b"{", 400, "not JSON"),
        (
            json.dumps({"host": "h", "action": "restart", "ids": [1], "user": "a", "shell": "x"}).encode(),
            400,
            "shell: not a field",
        ),
        (json.dumps({"host": "h", "action": "restart", "ids": [1]}).encode(), 400, "user: missing"),
        (
            json.dumps({"host": "h", "action": "reboot", "ids": [1], "user": "a"}).encode(),
            400,
            "action: 'reboot' is not one of",
        ),
        (json.dumps({"host": "h", "action": "restart", "ids": [], "user": "a"}).encode(), 400, "ids: [] is not"),
        (json.dumps({"host": "h", "action": "restart", "ids": [True], "user": "a"}).encode(), 400, "ids: [True]"),
        (json.dumps({"host": "h", "action": "restart", "ids": [100], "user": "a"}).encode(), 400, "ids: [100]"),
        (json.dumps({"host": "h", "action": "restart", "ids": [1, 1], "user": "a"}).encode(), 400, "twice"),
        (
            json.dumps({"host": "h", "action": "restart", "ids": "1", "user": "a"}).encode(),
            400,
            "ids: '1' is not a list",
        ),
        (json.dumps({"host": "h", "action": "drain", "ids": [1], "user": "a"}).encode(), 400, "takes no instances"),
        (json.dumps({"host": "h", "action": "start", "ids": [1], "user": "a b"}).encode(), 400, "user, token"),
        (
            json.dumps({"host": "h", "action": "start", "ids": [1], "user": "a", "confirm": "yes"}).encode(),
            400,
            "confirm: 'yes'",
        ),
        (b"{" + b" " * agent.MAX_BODY + b"}", 413, "over 4096 bytes"),
        (b"[" * 3000, 400, "not JSON"),
    ],
)
def test_a_bad_request_is_refused_naming_its_field(body, code, words):
    with pytest.raises(agent.RefusedError) as exc:
        agent.parse_request(body)
    assert exc.value.code == code and words in exc.value.body["error"]


def test_a_request_meant_for_another_host_is_refused_whatever_reached_this_one(tmp_path):
    """The door names the host it means: a host that said another's address gets nothing done."""
    a, h, _lines = make(tmp_path)
    with pytest.raises(agent.RefusedError) as exc:
        a.submit(dict(req(), host="gpu-2"))
    assert exc.value.code == 421 and exc.value.body["error"].startswith("host: this is gpu-1, not gpu-2")
    assert runlock.read(a.lock) is None and not h.commands("restart")


def state(active: bool) -> dict:
    return {"ActiveState": "active" if active else "inactive"}


def test_n_minus_1_counts_what_each_action_takes_down_while_it_runs():
    all_up = {i: state(True) for i in range(4)}
    one_down = {**all_up, 1: state(False)}
    assert agent.below_n1("restart", [2], all_up) == ""
    assert agent.below_n1("restart", [0, 2, 3], all_up) == ""  # one at a time
    assert agent.below_n1("stop", [2], all_up) == ""
    assert "would leave 2 of this host's 4 instances serving (isaac-sim-1 not serving), below N-1 = 3" in (
        agent.below_n1("restart", [2], one_down)
    )
    assert agent.below_n1("stop", [2, 3], all_up).startswith("stop of isaac-sim-2, isaac-sim-3 would leave 2")
    assert agent.below_n1("restart", [1], one_down) == ""  # not serving: taking it down costs nothing
    assert agent.below_n1("start", [1], one_down) == ""
    assert agent.below_n1("remove", [3], one_down) != ""
    # one instance: N-1 is 0, and emptying the host still asks
    assert agent.below_n1("stop", [0], {0: state(True)}).endswith(
        "would leave 0 of this host's 1 instances serving, none at all"
    )
    assert agent.below_n1("start", [0], {0: state(False)}) == ""


def test_a_restart_is_acknowledged_then_runs_through_the_lifecycle_and_says_how_it_went(tmp_path):
    a, h, lines = make(tmp_path)
    code, body = a.submit(req(token="ci"))
    assert code == 202 and body["state"] == "accepted" and len(body["id"]) == 16
    a.wait()
    rec = a.get(body["id"])
    assert rec["state"] == "succeeded" and rec["progress"] == 100 and rec["result"]["ok"]
    texts = [e["text"] for e in rec["events"]]
    assert texts[0] == "accepted: restart isaac-sim-2 by alice (token ci)"
    assert "restart: isaac-sim-2 (waits for its ready line)" in texts
    assert any(t.startswith("restart of isaac-sim-2 done in") for t in texts)
    assert [e["progress"] for e in rec["events"]] == sorted(e["progress"] for e in rec["events"])
    assert h.commands("restart") == ["systemctl restart isaac-sim@2.service"]
    # the host is free again, and the action is a line in the instance's own journal
    assert runlock.read(str(tmp_path / "lock.json")) is None
    assert ("isaac-sim@2.service", f"action {body['id']} restart isaac-sim-2 by alice (token ci): succeeded") in lines
    # kept on disk: a new agent (the service restarted) still tells it
    again, _h, _l = make(tmp_path)
    assert again.get(body["id"])["state"] == "succeeded"
    assert [r["id"] for r in again.recent()] == [body["id"]]


def test_the_agent_takes_the_guard_the_lifecycle_call_marks_its_job_under(tmp_path):
    a, _h, _lines = make(tmp_path)
    assert a.guard == runlock.guard_of(a.lock) == str(tmp_path / ".isaac-sim.guard")


def test_an_action_on_a_host_a_deploy_holds_is_refused_naming_the_deploy_and_changes_nothing(tmp_path):
    a, h, _lines = make(tmp_path)
    deploy = {"id": "ctl:1:2", "user": "bob", "controller": "ctl", "pid": 1, "started": "2", "play": "Deploy"}
    runlock.acquire(deploy, time.time(), 3600, path=a.lock, guard=a.guard, record_path="")
    with pytest.raises(agent.RefusedError) as exc:
        a.submit(req())
    assert exc.value.code == 409
    assert "gpu-1 is held by bob on ctl (ansible-playbook pid 1, play 'Deploy')" in exc.value.body["error"]
    assert not h.commands("restart") and runlock.read(a.lock)["id"] == "ctl:1:2"


def test_a_deploy_during_an_action_finds_the_host_held_by_it(tmp_path):
    """While the action runs, the lock names it; a playbook run is told who holds the host."""
    a, h, _lines = make(tmp_path)
    seen = []
    run = h.host.run

    def slow(argv):
        if argv[:2] == ["systemctl", "restart"]:
            me = {"id": "ctl:9:9", "user": "bob", "controller": "ctl", "pid": 9, "started": "9"}
            seen.append(runlock.acquire(me, time.time(), 3600, path=a.lock, guard=a.guard, record_path=""))
        return run(argv)

    h.host.run = slow
    _code, body = a.submit(req())
    a.wait()
    taken, holder, _note = seen[0]
    assert not taken and holder["agent"] == body["id"]
    assert runlock.holder_text(holder, time.time()).startswith(
        f"alice through the fleet API (action {body['id']}: restart isaac-sim-2)"
    )


def test_below_n_minus_1_needs_a_confirmation_and_nothing_runs_without_it(tmp_path):
    a, h, lines = make(tmp_path)
    h.units[1].update(ActiveState="inactive", SubState="dead")
    with pytest.raises(agent.RefusedError) as exc:
        a.submit(req())
    assert exc.value.code == 412 and exc.value.body["needs_confirm"] is True
    assert "below N-1 = 3" in exc.value.body["error"] and "confirm: true" in exc.value.body["error"]
    assert not h.commands("restart") and runlock.read(a.lock) is None
    assert "not confirmed" in lines[-1][1]
    code, body = a.submit(req(confirm=True))
    a.wait()
    assert code == 202 and a.get(body["id"])["state"] == "succeeded"
    assert "confirmed: restart of isaac-sim-2 would leave 2" in a.get(body["id"])["events"][0]["text"]


def test_an_instance_the_host_does_not_run_is_404_and_the_host_is_free_again(tmp_path):
    a, _h, _lines = make(tmp_path)
    with pytest.raises(agent.RefusedError) as exc:
        a.submit(req(ids=[7]))
    assert exc.value.code == 404 and "isaac-sim-7 not on gpu-1, which runs isaac-sim-0" in exc.value.body["error"]
    assert runlock.read(a.lock) is None


def test_a_failed_restart_is_reverted_by_the_lifecycle_and_reported(tmp_path):
    a, h, lines = make(tmp_path)
    # the instance never gets ready after its restart: the lifecycle reports it, the action says so
    h.files["/etc/isaac-sim/instance-2.env"] = (
        h.files["/etc/isaac-sim/instance-2.env"][0].replace("reg/isaac-sim:5.0.0", "reg/isaac-sim:never-ready"),
        0o644,
    )
    _code, body = a.submit(req())
    a.wait()
    rec = a.get(body["id"])
    assert rec["state"] == "failed" and not rec["result"]["ok"]
    assert "isaac-sim-2: isaac-sim-2 was not ready within 20 s" in rec["result"]["message"]
    assert rec["result"]["failed_instance"]["id"] == 2
    assert runlock.read(a.lock) is None
    assert lines[-1][1].endswith(rec["result"]["message"]) and ": failed: " in lines[-1][1]


@pytest.mark.parametrize("action", ["restart", "stop", "remove", "cleanup"])
def test_no_action_touches_an_instance_a_run_or_session_holds_and_the_host_is_free_again(tmp_path, action):
    a, h, lines = make(tmp_path)
    lifecycle.lend(h.host, 2, "session-olga")
    before = list(h.log)
    with pytest.raises(agent.RefusedError) as exc:
        a.submit(req(action, ids=[] if action == "cleanup" else [2], confirm=True))
    assert exc.value.code == 409 and "isaac-sim-2 is held by session-olga" in exc.value.body["error"]
    assert exc.value.body["held"] == [{"id": 2, "holder": "session-olga"}]
    assert h.log == before and runlock.read(a.lock) is None
    assert any("refused action" in line and "session-olga" in line for _unit, line in lines)


def test_a_claim_lends_one_ready_instance_to_a_session_at_once_and_gives_the_host_back(tmp_path):
    a, h, lines = make(tmp_path)
    code, body = a.submit(req("claim", ids=[2], holder="session-ab12"))
    assert code == 200 and body["state"] == "succeeded" and body["holder"] == "session-ab12"
    assert lifecycle.lent_to(h.host, 2) == "session-ab12" and runlock.read(a.lock) is None
    # nothing restarted: the instance was ready, and is handed over as it is
    assert not h.commands("restart") and not h.commands("stop")
    assert (layout.unit(2), "isaac-sim-2 claimed for session-ab12 by alice") in lines
    # the same instance again, for anyone: refused, naming who has it
    with pytest.raises(agent.RefusedError) as exc:
        a.submit(req("claim", ids=[2], holder="session-cd34"))
    assert exc.value.code == 409 and exc.value.body["held_by"] == "session-ab12"
    assert lifecycle.lent_to(h.host, 2) == "session-ab12" and runlock.read(a.lock) is None


def test_claims_of_one_instance_at_once_lend_it_once(tmp_path):
    a, h, _lines = make(tmp_path)
    codes = []

    def claim(n):
        try:
            codes.append(a.submit(req("claim", ids=[1], holder=f"session-s{n}"))[0])
        except agent.RefusedError as refused:
            codes.append(refused.code)

    threads = [threading.Thread(target=claim, args=(n,)) for n in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    # one lends it; the others found the host held by that claim, or the instance held
    assert sorted(codes) == [200] + [409] * 7, codes
    assert lifecycle.lent_to(h.host, 1).startswith("session-s") and runlock.read(a.lock) is None


def test_the_same_restart_sent_eight_times_at_once_runs_once_and_the_others_are_told_who_holds_the_host(tmp_path):
    a, h, _lines = make(tmp_path)
    # the restart runs until every request has had its answer: none can find the host free again
    answered, run = threading.Event(), h.host.run

    def held(argv):
        if argv[:2] == ["systemctl", "restart"]:
            answered.wait(10)
        return run(argv)

    h.host.run = held
    answers, together = [], threading.Barrier(8)

    def restart():
        together.wait(10)
        try:
            answers.append(a.submit(req())[:2])
        except agent.RefusedError as refused:
            answers.append((refused.code, refused.body))

    threads = [threading.Thread(target=restart) for _n in range(8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    answered.set()
    a.wait()
    assert sorted(code for code, _body in answers) == [202] + [409] * 7, answers
    [first] = [body["id"] for code, body in answers if code == 202]
    for code, body in answers:
        if code == 409:
            assert f"alice through the fleet API (action {first}: restart isaac-sim-2)" in body["error"], body
    assert h.commands("restart") == ["systemctl restart isaac-sim@2.service"]
    assert a.get(first)["state"] == "succeeded" and runlock.read(a.lock) is None


@pytest.mark.parametrize("why", ["drained", "not ready", "deploy", "not there"])
def test_a_claim_is_refused_with_nothing_changed(tmp_path, why):
    a, h, _lines = make(tmp_path)
    i, code = 1, 409
    if why == "drained":
        a.submit(req("drain", ids=[]))
    elif why == "not ready":
        h.markers.discard(1)
    elif why == "deploy":
        deploy = {"id": "ctl:1:2", "user": "bob", "controller": "ctl", "pid": 1, "started": "2", "play": "Deploy"}
        runlock.acquire(deploy, time.time(), 3600, path=a.lock, guard=a.guard, record_path="")
    else:
        i, code = 7, 404
    before = list(h.log)
    with pytest.raises(agent.RefusedError) as exc:
        a.submit(req("claim", ids=[i], holder="session-ab12"))
    assert exc.value.code == code, exc.value.body
    assert {"drained": "drained", "not ready": "not ready", "deploy": "held by bob"}.get(why, "not on") in str(
        exc.value.body["error"]
    )
    assert lifecycle.lent_to(h.host, i) is None and h.log == before
    if why != "deploy":
        assert runlock.read(a.lock) is None


def test_a_give_back_restarts_the_instance_clean_and_only_then_frees_it(tmp_path):
    a, h, lines = make(tmp_path)
    a.submit(req("claim", ids=[3], holder="session-ab12"))
    # another session's give-back of it is refused, and nothing restarts
    with pytest.raises(agent.RefusedError) as exc:
        a.submit(req("give_back", ids=[3], holder="session-cd34"))
    assert exc.value.code == 409 and not h.commands("restart")
    freed_before_ready = []
    start = h._start

    def spy(i):
        freed_before_ready.append(lifecycle.lent_to(h.host, i))
        return start(i)

    h._start = spy
    code, body = a.submit(req("give_back", ids=[3], holder="session-ab12"))
    assert code == 202
    a.wait()
    done = a.get(body["id"])
    assert done["state"] == "succeeded" and "restarted and free" in done["result"]["message"], done
    assert h.commands("restart") == [f"systemctl restart {layout.unit(3)}"]
    # still held while it restarted; free once ready
    assert freed_before_ready == ["session-ab12"] and lifecycle.lent_to(h.host, 3) is None
    # a give-back of what nobody holds changes nothing
    code, body = a.submit(req("give_back", ids=[3], holder="session-ab12"))
    assert code == 200 and "held by nobody" in body["result"]["message"]
    assert len(h.commands("restart")) == 1


def test_a_give_back_asked_again_while_it_runs_is_the_same_action_and_restarts_once(tmp_path):
    a, h, _lines = make(tmp_path)
    a.submit(req("claim", ids=[1], holder="session-ab12"))
    started, go_on = threading.Event(), threading.Event()
    start = h._start

    def slow(i):
        started.set()
        go_on.wait(10)
        return start(i)

    h._start = slow
    code, first = a.submit(req("give_back", ids=[1], holder="session-ab12"))
    assert code == 202 and started.wait(10)
    again = [a.submit(req("give_back", ids=[1], holder="session-ab12")) for _k in range(3)]
    go_on.set()
    a.wait()
    assert {(c, b["id"]) for c, b in again} == {(202, first["id"])}
    assert h.commands("restart") == [f"systemctl restart {layout.unit(1)}"] and lifecycle.lent_to(h.host, 1) is None


@pytest.mark.parametrize(
    ("over", "words"),
    [
        ({"action": "claim", "ids": [1, 2], "holder": "session-a"}, "takes one instance"),
        ({"action": "claim", "ids": [1], "holder": "olga"}, "holder: a session's name"),
        ({"action": "claim", "ids": [1], "holder": "session-a\n"}, "holder: a session's name"),
        ({"action": "claim", "ids": [1]}, "holder: a session's name"),
        ({"action": "restart", "ids": [1], "holder": "session-a"}, "only a claim or a give_back"),
    ],
)
def test_a_claim_s_request_is_checked_field_by_field(over, words):
    body = {"host": "gpu-1", "user": "alice", **over}
    with pytest.raises(agent.RefusedError) as exc:
        agent.parse_request(json.dumps(body).encode())
    assert exc.value.code == 400 and words in exc.value.body["error"]


def test_stop_start_and_remove_go_through_the_lifecycle_too(tmp_path):
    a, h, _lines = make(tmp_path)
    for action in ("stop", "start", "remove"):
        _code, body = a.submit(req(action, ids=[3]))
        a.wait()
        assert a.get(body["id"])["state"] == "succeeded", a.get(body["id"])
    assert h.units[3]["UnitFileState"] == "disabled" and "/etc/isaac-sim/instance-3.env" not in h.files
    # caches, logs and data stay: the agent never purges
    assert not any(line.startswith("rm /var/lib") for line in h.log)


def test_cleanup_removes_every_instance_through_the_lifecycle_once_confirmed_and_keeps_the_data(tmp_path):
    a, h, lines = make(tmp_path)
    with pytest.raises(agent.RefusedError) as exc:
        a.submit(req("cleanup", ids=()))
    # always a confirmation, even with every instance serving (it empties the host)
    assert exc.value.code == 412 and exc.value.body["needs_confirm"] is True
    assert "cleanup removes every instance of gpu-1 (4)" in exc.value.body["error"]
    assert not h.commands("stop") and runlock.read(a.lock) is None
    with pytest.raises(agent.RefusedError) as exc:
        a.submit(req("cleanup", ids=[1]))
    assert exc.value.code == 400 and "takes no instances" in exc.value.body["error"]
    code, body = a.submit(req("cleanup", ids=(), confirm=True))
    a.wait()
    rec = a.get(body["id"])
    assert code == 202 and rec["state"] == "succeeded", rec
    assert rec["ids"] == [0, 1, 2, 3] and rec["what"].startswith("cleanup gpu-1: remove isaac-sim-0, isaac-sim-1")
    for i in range(4):
        assert h.units[i]["UnitFileState"] == "disabled" and f"/etc/isaac-sim/instance-{i}.env" not in h.files
    assert not any(line.startswith("rm /var/lib") for line in h.log)
    assert runlock.read(a.lock) is None
    # each instance's journal has the line; a cleanup of an empty host is done at once
    assert {unit for unit, line in lines if ": succeeded" in line} >= {f"isaac-sim@{i}.service" for i in range(4)}
    code, body = a.submit(req("cleanup", ids=()))
    assert code == 200 and "runs no instance; nothing to remove" in body["result"]["message"]
    assert runlock.read(a.lock) is None


def test_drain_and_undrain_are_kept_and_take_no_lock(tmp_path):
    a, _h, lines = make(tmp_path)
    code, body = a.submit(req("drain", ids=()))
    assert code == 200 and body["state"] == "succeeded" and a.drained_by()["by"] == "alice"
    # the host's status says so (the status endpoint reads the same file in its config directory)
    from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import fleet_status

    assert fleet_status.read_drained(str(tmp_path))["by"] == "alice"
    a.submit(req("undrain", ids=()))
    assert a.drained_by() is None and len(a.recent()) == 2
    assert lines[-1][1].endswith("undrain of gpu-1 by alice: succeeded")


def test_an_action_the_agent_did_not_see_end_is_said_interrupted_and_its_hold_given_back(tmp_path):
    a, _h, _lines = make(tmp_path)
    rec = {"id": "0123456789abcdef", "state": "running", "progress": 10, "events": [], "what": "restart isaac-sim-2"}
    a._save(rec)
    runlock.acquire({"id": rec["id"], "agent": rec["id"]}, time.time(), 0, path=a.lock, guard=a.guard, record_path="")
    again, _h, _l = make(tmp_path)
    got = again.get(rec["id"])
    assert got["state"] == "interrupted" and "the agent stopped while this action ran" in got["events"][-1]["text"]
    assert runlock.read(a.lock) is None


def test_a_hold_left_by_an_agent_process_that_is_gone_is_given_back_at_the_next_start(tmp_path):
    """Killed between taking the hold and writing its action down: no record says so, the hold's own
    process does (its pid is gone, or is another process now)."""
    a, _h, _lines = make(tmp_path)
    gone = {"id": "fedcba9876543210", "agent": "fedcba9876543210", "pid": 2**22 + 7, "started": "1"}
    runlock.acquire(gone, time.time(), 0, path=a.lock, guard=a.guard, record_path="")
    make(tmp_path)
    assert runlock.read(a.lock) is None
    # a live one (this process, as the agent that runs now) is left as it is
    mine = {"id": "0000000000000001", "agent": "0000000000000001", "pid": os.getpid(),
            "started": runlock.start_time(os.getpid())}  # fmt: skip
    runlock.acquire(mine, time.time(), 0, path=a.lock, guard=a.guard, record_path="")
    make(tmp_path)
    assert runlock.read(a.lock)["id"] == mine["id"]


def test_an_action_that_cannot_start_gives_the_host_back_and_says_so(tmp_path, monkeypatch):
    a, _h, _lines = make(tmp_path)

    def no_thread(self):
        raise RuntimeError("can't start new thread")

    monkeypatch.setattr(threading.Thread, "start", no_thread)
    with pytest.raises(RuntimeError):
        a.submit(req())
    monkeypatch.undo()
    assert runlock.read(a.lock) is None
    [rec] = a.recent()
    assert rec["state"] == "failed" and rec["result"]["message"].startswith("not started: RuntimeError")


def test_an_outcome_that_cannot_be_written_still_ends_the_action_and_its_hold(tmp_path, monkeypatch):
    a, _h, lines = make(tmp_path)
    save = a._save

    def full(rec):
        if rec["state"] in ("succeeded", "failed"):
            raise OSError(28, "No space left on device")
        save(rec)

    monkeypatch.setattr(a, "_save", full)
    _code, body = a.submit(req())
    a.wait()
    assert runlock.read(a.lock) is None
    # still told by this process, ended
    assert a.get(body["id"])["state"] == "succeeded" and a.events(body["id"], 0, wait=0)[1] is True
    assert any("could not keep its outcome" in line for _unit, line in lines)


def test_events_are_followed_as_they_come_until_the_action_ends(tmp_path):
    a, h, _lines = make(tmp_path)
    gate = threading.Event()
    run = h.host.run

    def held(argv):
        if argv[:2] == ["systemctl", "restart"]:
            gate.wait(5)
        return run(argv)

    h.host.run = held
    _code, body = a.submit(req())
    first, ended = a.events(body["id"], 0, wait=0.2)
    assert not ended and first[0]["state"] in ("accepted", "running")
    gate.set()
    seen, ended = len(first), False
    deadline = time.monotonic() + 10
    while not ended and time.monotonic() < deadline:
        new, ended = a.events(body["id"], seen, wait=0.5)
        seen += len(new)
    assert ended and seen == len(a.get(body["id"])["events"])


# --- the channel


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    return make_pki(tmp_path_factory.mktemp("pki"), agent.CLIENT_NAME)


@pytest.fixture
def channel(tmp_path, pki):
    a, h, lines = make(tmp_path, data_root=str(tmp_path / "data"), pipe=Container(tmp_path / "inside"))
    said = []
    ctx = agent.tls_context(str(pki / "agent.crt"), str(pki / "agent.key"), str(pki / "ca.crt"))
    server = agent.Server(
        ("127.0.0.1", 0), agent.handler(a), ctx, [agent.ipaddress.ip_network("127.0.0.0/8")], log=said.append
    )
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield server, a, h, said
    server.shutdown()
    server.server_close()


def client(pki, cert=None):
    ctx = ssl.create_default_context(cafile=str(pki / "ca.crt"))
    if cert:
        ctx.load_cert_chain(*cert)
    return ctx


def door(pki):
    return str(pki / f"{agent.CLIENT_NAME}.crt"), str(pki / f"{agent.CLIENT_NAME}.key")


def ask(server, ctx, method="GET", path="/health", body=None):
    conn = http.client.HTTPSConnection("127.0.0.1", server.server_address[1], context=ctx, timeout=10)
    try:
        conn.request(method, path, body=json.dumps(body) if body is not None else None)
        answer = conn.getresponse()
        return answer.status, answer.read()
    finally:
        conn.close()


def test_the_front_door_s_certificate_opens_the_channel(channel, pki):
    server, a, _h, _said = channel
    status, body = ask(server, client(pki, door(pki)))
    assert status == 200 and json.loads(body)["host"] == "gpu-1"
    status, body = ask(
        server,
        client(pki, door(pki)),
        "POST",
        "/actions",
        {"host": "gpu-1", "action": "restart", "ids": [2], "user": "alice"},
    )
    assert status == 202
    action_id = json.loads(body)["id"]
    # the events, followed over the channel until the action ends
    status, stream = ask(server, client(pki, door(pki)), path=f"/actions/{action_id}/events?follow=1")
    events = [json.loads(line) for line in stream.decode().splitlines()]
    assert status == 200 and events[-1]["state"] == "succeeded" and events[-1]["progress"] == 100
    status, body = ask(
        server, client(pki, door(pki)), "POST", "/actions", {"host": "gpu-1", "action": "restart", "ids": [2]}
    )
    assert status == 400 and json.loads(body)["error"] == "user: missing"


@pytest.mark.parametrize(
    ("who", "why"),
    [
        (None, "TLS"),
        ("someone else", "certificate of 'someone else', not the front door's"),
        ("other-door", "TLS"),
    ],
)
def test_any_other_client_is_refused_before_a_byte_of_http(channel, pki, who, why):
    server, _a, h, said = channel
    cert = None
    if who == "someone else":
        cert = (str(pki / "someone else.crt"), str(pki / "someone else.key"))
    elif who == "other-door":
        cert = (
            str(pki / "other-door" / f"{agent.CLIENT_NAME}.crt"),
            str(pki / "other-door" / f"{agent.CLIENT_NAME}.key"),
        )
    with pytest.raises((ssl.SSLError, ConnectionError, http.client.HTTPException, OSError)):
        ask(
            server,
            client(pki, cert),
            "POST",
            "/actions",
            {"host": "gpu-1", "action": "stop", "ids": [0], "user": "mallory"},
        )
    deadline = time.monotonic() + 5
    while not said and time.monotonic() < deadline:
        time.sleep(0.05)
    assert said and why in said[-1]
    assert not h.commands("stop")


def test_a_client_outside_the_allowed_networks_is_not_even_answered(tmp_path, pki):
    a, _h, _lines = make(tmp_path)
    said = []
    ctx = agent.tls_context(str(pki / "agent.crt"), str(pki / "agent.key"), str(pki / "ca.crt"))
    server = agent.Server(
        ("127.0.0.1", 0), agent.handler(a), ctx, [agent.ipaddress.ip_network("10.9.0.0/24")], log=said.append
    )
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        with pytest.raises((ssl.SSLError, ConnectionError, OSError)):
            ask(server, client(pki, door(pki)))
        assert said == ["refused 127.0.0.1: not in the allowed networks"]
    finally:
        server.shutdown()
        server.server_close()


def test_a_client_that_never_finishes_its_handshake_holds_only_its_own_thread(channel, pki):
    server, _a, _h, _said = channel
    server.handshake_s = 0.5
    idle = socket.create_connection(server.server_address[:2])
    try:
        status, _body = ask(server, client(pki, door(pki)))
        assert status == 200
    finally:
        idle.close()


def test_the_agent_s_code_is_what_it_imports_and_runs_from_its_copy_without_ansible(tmp_path):
    """layout.AGENT_CODE is the closure of agent.py's imports (nothing missing on a host, nothing more
    shipped), and a copy of those files alone, with the standard library alone (-S), starts."""
    import ast
    import shutil
    import sys
    from pathlib import Path

    from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout

    base = Path(agent.__file__).resolve().parents[1]
    prefix = "ansible_collections.isaacsim.fleet.plugins.module_utils."
    seen, todo = set(), ["instance/agent.py"]
    while todo:
        rel = todo.pop()
        if rel in seen:
            continue
        seen.add(rel)
        for node in ast.walk(ast.parse((base / rel).read_text())):
            if isinstance(node, ast.ImportFrom) and (node.module or "").startswith(prefix):
                package = node.module[len(prefix) :].replace(".", "/")
                for alias in node.names:
                    todo.append(
                        f"{package}/{alias.name}.py"
                        if (base / package / f"{alias.name}.py").exists()
                        else f"{package}.py"
                    )
    inits = {f"{rel.split('/')[0]}/__init__.py" for rel in seen}
    assert sorted(seen | inits) == sorted(layout.AGENT_CODE)
    copy = tmp_path / layout.AGENT_PACKAGE
    for rel in layout.AGENT_CODE:
        (copy / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(base / rel, copy / rel)
    done = subprocess.run(
        [
            sys.executable,
            "-S",
            "-m",
            "ansible_collections.isaacsim.fleet.plugins.module_utils.instance.agent",
            "--help",
        ],
        env={"PYTHONPATH": str(tmp_path)},
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0 and "The host's action agent" in done.stdout, done.stderr


def test_more_clients_at_once_than_the_agent_serves_are_closed_and_the_next_one_is_served(channel, pki):
    server, _a, _h, said = channel
    held = [socket.create_connection(server.server_address[:2]) for _client in range(agent.MAX_CLIENTS)]
    try:
        late = socket.create_connection(server.server_address[:2])
        late.settimeout(5)
        assert late.recv(1) == b""  # closed at once
        late.close()
        assert any("clients at once already" in line for line in said)
    finally:
        for sock in held:
            sock.close()
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:
        try:
            if ask(server, client(pki, door(pki)))[0] == 200:
                break
        except OSError:
            time.sleep(0.2)
    else:
        raise AssertionError("not served again once the others went")


# --- a session's files: GET and DELETE its stashes, PUT a tar into the instance it holds

HOLDER = "session-ab12"
PASSWD = Path("/etc/passwd").read_bytes()


class Container:
    """docker exec -i ... tar ... -C DEST -xf - as the container would run it: the real tar, with `inside`
    for DEST (what the container's Documents mount is); each call written down. answer: (rc, out, err)
    instead of running it."""

    def __init__(self, inside, answer=None):
        self.inside, self.answer, self.calls = inside, answer, []

    def __call__(self, argv, stdin):
        self.calls.append(list(argv))
        if self.answer:
            return self.answer
        os.makedirs(self.inside, exist_ok=True)
        tar = argv[argv.index("tar") :]
        tar[tar.index("-C") + 1] = str(self.inside)
        done = subprocess.run(tar, stdin=stdin, capture_output=True, text=True, check=False)
        return done.returncode, done.stdout, done.stderr


def files_agent(tmp_path, answer=None, **over):
    """An agent whose data root is in tmp_path, its containers' put done by a Container."""
    box = Container(tmp_path / "inside", answer)
    a, h, lines = make(tmp_path, data_root=str(tmp_path / "data"), pipe=box, **over)
    return a, h, lines, box


def docker(h, a, i=2, running=True, source=None, rw=True, user="1234:1234"):
    """docker inspect of instance i's container as Docker answers it: its documents directory mounted."""
    c = {
        "Id": "c0ffee" + "0" * 58,
        "State": {"Running": running},
        "Config": {"User": user},
        "Mounts": [
            {
                "Type": "bind",
                "Source": f"{a.data_root}/instance-{i}/logs",
                "Destination": "/isaac-sim/logs",
                "RW": True,
            },
            {
                "Type": "bind",
                "Source": source or layout.documents_dir(i, a.data_root),
                "Destination": "/isaac-sim/Documents",
                "RW": rw,
            },
        ],
    }
    run = h.host.run

    def inspect(argv):
        if argv[:2] == ["docker", "inspect"]:
            if argv[-1] != layout.container(i):
                return 1, "[]", f"Error: No such container: {argv[-1]}"
            return 0, json.dumps([c]), ""
        return run(argv)

    h.host.run = inspect
    return c


def stash(a, files, n=1, holder=HOLDER):
    """A stash of `holder` with files {relative path: bytes or text}."""
    top = layout.files_stash(holder, n, a.data_root)
    os.makedirs(top)
    for rel, data in files.items():
        os.makedirs(os.path.dirname(os.path.join(top, rel)), exist_ok=True)
        with open(os.path.join(top, rel), "wb") as fh:
            fh.write(data.encode() if isinstance(data, str) else data)
    return top


def members(path) -> dict:
    """{name: (type, mode, uid, gid, uname, gname, content or None)} of a tar file."""
    out = {}
    with tarfile.open(path) as tar:
        for m in tar:
            data = tar.extractfile(m).read() if m.isreg() else None
            out[m.name] = (m.type, m.mode, m.uid, m.gid, m.uname, m.gname, data)
    return out


def tar_of(entries) -> bytes:
    """A tar of [(name, type, content)] made here (the door's side)."""
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w") as tar:
        for name, kind, data in entries:
            info = tarfile.TarInfo(name)
            info.type = kind
            if kind == tarfile.SYMTYPE:
                info.linkname = data
                tar.addfile(info)
            elif kind == tarfile.DIRTYPE:
                info.mode = 0o755
                tar.addfile(info)
            else:
                info.size, info.mode = len(data), 0o644
                tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def test_get_files_is_a_tar_of_the_stash_with_relative_names_no_owner_and_regular_files_and_directories_only(
    tmp_path,
):
    a, _h, lines, _box = files_agent(tmp_path)
    top = stash(a, {"a.txt": "hello", "sub/b.bin": b"\x00\x01\x02"})
    os.chmod(os.path.join(top, "a.txt"), 0o4755)
    # hostile: links to the host's files and directories, a fifo, a second name of a file
    os.symlink("/etc/passwd", os.path.join(top, "passwd"))
    os.symlink("/etc", os.path.join(top, "etc"))
    os.symlink("../../../../../../../etc/passwd", os.path.join(top, "sub", "up"))
    os.mkfifo(os.path.join(top, "sub", "pipe"))
    os.link(os.path.join(top, "a.txt"), os.path.join(top, "z-again.txt"))
    path, said = a.files_tar(HOLDER, 10**6)
    try:
        got = members(path)
        assert os.path.dirname(path) == a.tmp_dir
    finally:
        os.unlink(path)
    assert sorted(got) == ["a.txt", "sub", "sub/b.bin"]
    assert got["a.txt"] == (tarfile.REGTYPE, 0o755, 0, 0, "", "", b"hello")
    assert got["sub"][:6] == (tarfile.DIRTYPE, 0o755, 0, 0, "", "")
    assert got["sub/b.bin"][6] == b"\x00\x01\x02"
    assert not any(PASSWD in (m[6] or b"") for m in got.values())
    assert said == {"bytes": 8, "members": 3, "skipped": 5, "over": False}
    assert (
        "",
        f"files of {HOLDER}: 3 sent (8 bytes), 5 left out (links, devices, fifos, hard links, too deep)",
    ) in lines
    # the stash stays as it is until the door removes it
    assert sorted(os.listdir(top)) == ["a.txt", "etc", "passwd", "sub", "z-again.txt"]


def test_a_stash_that_is_itself_a_link_is_not_read(tmp_path):
    a, _h, _lines, _box = files_agent(tmp_path)
    os.makedirs(os.path.join(a.data_root, layout.FILES_DIR))
    os.symlink("/etc", layout.files_dir(HOLDER, a.data_root))
    path, said = a.files_tar(HOLDER, 10**9)
    try:
        assert members(path) == {} and said["members"] == 0
    finally:
        os.unlink(path)


def test_get_files_over_max_is_413_with_the_total_and_none_is_404_and_no_tar_is_left(tmp_path):
    a, _h, _lines, _box = files_agent(tmp_path)
    with pytest.raises(agent.RefusedError) as exc:
        a.files_tar(HOLDER, 10)
    assert exc.value.code == 404 and exc.value.body == {"error": f"no files of {HOLDER} on gpu-1"}
    stash(a, {"a": "12345", "b/c": "678901"})
    with pytest.raises(agent.RefusedError) as exc:
        a.files_tar(HOLDER, 10)
    assert exc.value.code == 413 and exc.value.body["bytes"] == 11 and "over 10" in exc.value.body["error"]
    assert os.listdir(a.tmp_dir) == []


def test_get_files_merges_a_later_stash_over_an_earlier_one_so_nothing_is_lost(tmp_path):
    a, _h, _lines, _box = files_agent(tmp_path)
    stash(a, {"x": "old", "only-old": "o", "d/inner": "gone under a file", "f": "was a file"})
    stash(a, {"x": "new", "d": "a file now", "f/inside": "a directory now"}, n=2)
    path, _said = a.files_tar(HOLDER, 10**6)
    try:
        got = {name: m[6] for name, m in members(path).items()}
    finally:
        os.unlink(path)
    assert got == {"d": b"a file now", "f": None, "f/inside": b"a directory now", "only-old": b"o", "x": b"new"}


def test_delete_files_removes_every_stash_of_the_session_and_nothing_a_link_in_it_names(tmp_path):
    a, _h, lines, _box = files_agent(tmp_path)
    outside = tmp_path / "outside"
    outside.mkdir()
    (outside / "keep").write_text("not theirs")
    top = stash(a, {"a": "1"})
    os.symlink(str(outside), os.path.join(top, "out"))
    stash(a, {"b": "2"}, n=2)
    other = stash(a, {"c": "3"}, holder="session-cd34")
    assert a.files_remove(HOLDER) is True
    assert os.listdir(os.path.join(a.data_root, layout.FILES_DIR)) == ["session-cd34"] and os.path.isdir(other)
    assert (outside / "keep").read_text() == "not theirs"
    assert a.files_remove(HOLDER) is False
    assert [line for _unit, line in lines[-2:]] == [f"files of {HOLDER}: removed", f"files of {HOLDER}: none to remove"]


def test_a_piped_command_is_fed_its_file_found_off_path_stopped_at_its_time_and_read_as_bytes(monkeypatch, tmp_path):
    monkeypatch.setenv("PATH", str(tmp_path))  # the agent's unit may have no /usr/bin on its PATH
    fed = tmp_path / "fed"
    fed.write_bytes(b"ok \xff\r\n")
    with open(fed, "rb") as fh:
        # bytes as they are, what is not UTF-8 replaced (never an error), a carriage return kept
        assert agent.run_piped(["cat"], fh) == (0, "ok \ufffd\r\n", "")
    with open(fed, "rb") as fh:
        assert agent.run_piped(["sleep", "5"], fh, timeout=0.2) == (124, "", "sleep: still running after 0 s; stopped")
        assert agent.run_piped(["no-such-command-here"], fh) == (127, "", "no-such-command-here: not found")


def test_put_files_extracts_in_the_running_container_as_its_user_into_its_documents_mount(tmp_path):
    a, h, lines, box = files_agent(tmp_path)
    lifecycle.lend(h.host, 2, HOLDER)
    c = docker(h, a)
    body = tar_of(
        [
            ("notes.txt", tarfile.REGTYPE, b"mine\n"),
            ("scenes", tarfile.DIRTYPE, None),
            ("scenes/a.usd", tarfile.REGTYPE, b"#usda 1.0\n"),
        ]
    )
    assert a.files_put(HOLDER, 2, io.BytesIO(body), len(body)) == {"put": 3, "bytes": len(body)}
    # the very container inspected (its id), its configured user, the destination of the documents mount
    assert box.calls == [
        ["docker", "exec", "-i", "--user", "1234:1234", c["Id"], "tar", "--no-same-owner", "-C", "/isaac-sim/Documents"]
        + ["-xf", "-"]
    ]
    assert (tmp_path / "inside" / "scenes" / "a.usd").read_text() == "#usda 1.0\n"
    assert (layout.unit(2), f"files of {HOLDER}: 3 put into isaac-sim-2 ({len(body)} bytes)") in lines
    assert os.listdir(a.tmp_dir) == []
    # a container that runs as the image's user (root on 4.x): no --user, docker exec runs as it does
    docker(h, a, user="")
    a.files_put(HOLDER, 2, io.BytesIO(body), len(body))
    assert "--user" not in box.calls[-1]


class NotRead(io.RawIOBase):
    def read(self, *_args):
        raise AssertionError("the body was read")


@pytest.mark.parametrize(
    ("why", "code", "words"),
    [
        ("lent to nobody", 409, "isaac-sim-2 is held by nobody, not session-ab12"),
        ("lent to another", 409, "isaac-sim-2 is held by session-cd34, not session-ab12"),
        ("too big", 413, "over 20000"),
        ("not configured", 404, "isaac-sim-7 not on gpu-1"),
        ("not mounted", 409, "documents is not mounted in isaac-sim-2"),
        ("read-only", 409, "documents is mounted read-only in isaac-sim-2"),
        ("stopped", 409, "isaac-sim-2 is not running"),
        ("a link", 400, "'notes.txt': only regular files and directories"),
        ("a way out", 400, "'../escape': not a relative path"),
        ("absolute", 400, "'/etc/cron.d/x': not a relative path"),
        ("not a tar", 400, "the body is not a tar"),
        ("tar fails", 502, "tar in isaac-sim-2 failed (exit 2): tar: scenes: Cannot mkdir: Disk quota exceeded"),
    ],
)
def test_put_files_is_refused_with_nothing_run_in_the_container(tmp_path, why, code, words):
    answer = (2, "", "tar: scenes: Cannot mkdir: Disk quota exceeded\ntar: Exiting with failure status")
    a, h, lines, box = files_agent(tmp_path, answer if why == "tar fails" else None, files_max_bytes=20000)
    i = 7 if why == "not configured" else 2
    if why != "lent to nobody":
        lifecycle.lend(h.host, 2, "session-cd34" if why == "lent to another" else HOLDER)
    docker(
        h,
        a,
        running=why != "stopped",
        rw=why != "read-only",
        source="/var/lib/elsewhere" if why == "not mounted" else None,
    )
    entries = [("notes.txt", tarfile.REGTYPE, b"mine\n")]
    if why == "a link":
        entries = [("notes.txt", tarfile.SYMTYPE, "/etc/passwd")]
    elif why == "a way out":
        entries.append(("../escape", tarfile.REGTYPE, b"x"))
    elif why == "absolute":
        entries.append(("/etc/cron.d/x", tarfile.REGTYPE, b"x"))
    body = b"hello, not a tar" * 40 if why == "not a tar" else tar_of(entries)
    length = 20001 if why == "too big" else len(body)
    with pytest.raises(agent.RefusedError) as exc:
        a.files_put(HOLDER, i, NotRead() if why == "too big" else io.BytesIO(body), length)
    assert exc.value.code == code and words in exc.value.body["error"], exc.value.body
    assert len(box.calls) == (why == "tar fails") and os.listdir(a.tmp_dir) == []
    if why == "tar fails":
        assert exc.value.body["stderr"].endswith("tar: Exiting with failure status")
        assert lines[-1] == (
            layout.unit(2),
            f"files of {HOLDER}: put into isaac-sim-2 failed (exit 2): tar: scenes: Cannot mkdir: Disk quota exceeded"
            " / tar: Exiting with failure status",
        )


def test_put_files_of_a_claim_that_ended_while_its_body_came_puts_nothing(tmp_path):
    a, h, _lines, box = files_agent(tmp_path)
    lifecycle.lend(h.host, 2, HOLDER)
    docker(h, a)
    body = tar_of([("notes.txt", tarfile.REGTYPE, b"mine\n")])

    class EndsTheClaim(io.BytesIO):
        def read(self, *args):
            lifecycle.unlend(h.host, 2, HOLDER)
            lifecycle.lend(h.host, 2, "session-cd34")
            return super().read(*args)

    with pytest.raises(agent.RefusedError) as exc:
        a.files_put(HOLDER, 2, EndsTheClaim(body), len(body))
    assert exc.value.code == 409 and "held by session-cd34 now" in exc.value.body["error"] and box.calls == []


@pytest.mark.parametrize(
    ("query", "names", "words"),
    [
        ("max=1&x=2", ("max",), "'x': not a parameter"),
        ("max=1&max=2", ("max",), "max: given twice"),
        ("max=-1", ("max",), "max: '-1' is not a number"),
        ("max", ("max",), "max: '' is not a number"),
        ("instance=1", (), "(its parameters: none)"),
    ],
)
def test_a_query_is_strict(query, names, words):
    with pytest.raises(agent.RefusedError) as exc:
        agent.parse_query(query, names)
    assert exc.value.code == 400 and words in exc.value.body["error"]
    assert agent.parse_query("max=10&instance=2", ("max", "instance")) == {"max": 10, "instance": 2}


def test_a_give_back_through_the_agent_moves_the_session_s_files_and_a_failed_move_keeps_the_claim(tmp_path):
    a, h, _lines, _box = files_agent(tmp_path)
    real_files(h, a.data_root)
    docs = documents(a.data_root, 3)
    a.submit(req("claim", ids=[3], holder=HOLDER))
    _code, body = a.submit(req("give_back", ids=[3], holder=HOLDER))
    a.wait()
    assert a.get(body["id"])["result"] == {
        "ok": True,
        "message": f"isaac-sim-3 given back by {HOLDER}: restarted and free",
        "held": False,
    }
    assert os.listdir(docs) == [] and "notes.txt" in os.listdir(layout.files_dir(HOLDER, a.data_root))
    # the stash there, the same session's later files could not move: it stays the session's
    documents(a.data_root, 1)
    real_files(h, a.data_root, fail={"mv": (1, "", "mv: No space left on device")})
    a.submit(req("claim", ids=[1], holder=HOLDER))
    _code, body = a.submit(req("give_back", ids=[1], holder=HOLDER))
    a.wait()
    result = a.get(body["id"])["result"]
    assert (
        not result["ok"]
        and result["held"] is True
        and result["message"].startswith(f"isaac-sim-1 not given back by {HOLDER}: could not move")
    )
    assert lifecycle.lent_to(h.host, 1) == HOLDER


def send(server, ctx, method, path, data=b"", headers=None):
    conn = http.client.HTTPSConnection("127.0.0.1", server.server_address[1], context=ctx, timeout=10)
    try:
        conn.request(method, path, body=data, headers=headers or {})
        answer = conn.getresponse()
        return answer.status, dict(answer.getheaders()), answer.read()
    finally:
        conn.close()


def test_the_files_endpoints_over_the_channel(channel, pki):
    server, a, h, said = channel
    ctx = client(pki, door(pki))
    stash(a, {"notes.txt": "mine\n"})
    os.symlink("/etc/passwd", os.path.join(layout.files_dir(HOLDER, a.data_root), "passwd"))
    status, headers, data = send(server, ctx, "GET", f"/files/{HOLDER}")
    assert status == 200 and headers["Content-Type"] == "application/x-tar"
    assert int(headers["Content-Length"]) == len(data)
    with tarfile.open(fileobj=io.BytesIO(data)) as tar:
        assert tar.getnames() == ["notes.txt"] and tar.extractfile("notes.txt").read() == b"mine\n"
    assert PASSWD not in data and os.listdir(a.tmp_dir) == []
    for path, code, words in [
        (f"/files/{HOLDER}?max=2", 413, "over 2"),
        (f"/files/{HOLDER}?max=2&all=1", 400, "'all': not a parameter"),
        ("/files/olga", 400, "holder: a session's name"),
        ("/files/session-ab12/x", 404, "no such path"),
        ("/files/session-cd34", 404, "no files of session-cd34"),
    ]:
        status, _headers, data = send(server, ctx, "GET", path)
        assert status == code and words in json.loads(data)["error"], (path, data)
    # a put into the instance the session holds
    lifecycle.lend(h.host, 2, HOLDER)
    docker(h, a)
    body = tar_of([("back.txt", tarfile.REGTYPE, b"again\n")])
    status, _headers, data = send(server, ctx, "PUT", f"/files/{HOLDER}?instance=2", body)
    assert status == 200 and json.loads(data) == {"put": 1, "bytes": len(body)}
    status, _headers, data = send(server, ctx, "PUT", f"/files/{HOLDER}?instance=3", body)
    assert status == 409 and "isaac-sim-3 is held by nobody" in json.loads(data)["error"]
    status, _headers, data = send(server, ctx, "PUT", f"/files/{HOLDER}", body)
    assert status == 400 and "instance:" in json.loads(data)["error"]
    # too big: refused on its Content-Length, before a byte of the body
    conn = http.client.HTTPSConnection("127.0.0.1", server.server_address[1], context=ctx, timeout=10)
    try:
        conn.putrequest("PUT", f"/files/{HOLDER}?instance=2")
        conn.putheader("Content-Length", str(agent.FILES_MAX_BYTES + 1))
        conn.endheaders()
        answer = conn.getresponse()
        assert answer.status == 413 and json.loads(answer.read())["bytes"] == agent.FILES_MAX_BYTES + 1
    finally:
        conn.close()
    status, _headers, data = send(server, ctx, "DELETE", f"/files/{HOLDER}?now=1")
    assert status == 400
    assert [json.loads(send(server, ctx, "DELETE", f"/files/{HOLDER}")[2]) for _n in range(2)] == [
        {"removed": True},
        {"removed": False},
    ]
    status, _headers, data = send(server, ctx, "DELETE", "/actions")
    assert status == 404


def expect_continue(server, ctx, path, body):
    """A PUT that says Expect: 100-continue, as the door sends one, its body sent only on 100 Continue:
    (the first status line that came, the final answer's status and JSON)."""
    conn = ctx.wrap_socket(socket.create_connection(server.server_address[:2], timeout=10), server_hostname="127.0.0.1")

    def until(done) -> bytes:
        got = b""
        while not done(got):
            chunk = conn.recv(65536)
            if not chunk:
                break
            got += chunk
        return got

    try:
        conn.sendall(
            f"PUT {path} HTTP/1.1\r\nHost: agent\r\nContent-Length: {len(body)}\r\n"
            "Expect: 100-continue\r\n\r\n".encode()
        )
        first = until(lambda got: b"\r\n\r\n" in got)
        answer = first
        if first.startswith(b"HTTP/1.1 100 "):
            conn.sendall(body)
            answer = first.partition(b"\r\n\r\n")[2]
        answer += until(lambda _got: False)  # to the connection's end
        head, _sep, data = answer.partition(b"\r\n\r\n")
        return first.split(b"\r\n", 1)[0], int(head.split(b" ", 2)[1]), json.loads(data)
    finally:
        conn.close()


def test_a_put_that_says_expect_100_continue_is_refused_before_its_body_or_told_to_go_on(channel, pki):
    server, a, h, _said = channel
    ctx = client(pki, door(pki))
    docker(h, a)
    inspected, run = [], h.host.run

    def counted(argv):
        if argv[:2] == ["docker", "inspect"]:
            inspected.append(argv[-1])
        return run(argv)

    h.host.run = counted
    body = tar_of([("back.txt", tarfile.REGTYPE, b"again\n")])
    # not held by that session: the answer comes before a byte of the body
    first, status, answer = expect_continue(server, ctx, f"/files/{HOLDER}?instance=2", body)
    assert first.startswith(b"HTTP/1.1 409") and status == 409 and "held by nobody" in answer["error"]
    lifecycle.lend(h.host, 2, HOLDER)
    first, status, answer = expect_continue(server, ctx, f"/files/{HOLDER}?instance=2", body)
    assert first == b"HTTP/1.1 100 Continue" and (status, answer) == (200, {"put": 1, "bytes": len(body)})
    assert Path(a.pipe.inside, "back.txt").read_bytes() == b"again\n"
    # its container inspected once, before 100 Continue, not again once the body came
    assert inspected == ["isaac-sim-2"]
    # a put without Expect is checked where its body is read, once too
    status, _headers, data = send(server, ctx, "PUT", f"/files/{HOLDER}?instance=2", body)
    assert status == 200 and json.loads(data) == {"put": 1, "bytes": len(body)}
    assert inspected == ["isaac-sim-2"] * 2


def test_a_stash_the_agent_may_not_read_is_an_error_never_an_empty_tar(tmp_path, monkeypatch):
    """Said empty, the door would keep nothing and remove the stash."""
    a, _h, lines, _box = files_agent(tmp_path)
    top = stash(a, {"a": "1"})
    real_open = os.open

    def refused(path, flags, *args, **kwargs):
        if path == top:
            raise PermissionError(13, "Permission denied", path)
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(agent.os, "open", refused)
    with pytest.raises(PermissionError):
        a.files_tar(HOLDER, 10**6)
    monkeypatch.undo()
    assert os.listdir(a.tmp_dir) == [] and not any("sent" in line for _unit, line in lines)
