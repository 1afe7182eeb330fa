"""The fleet's API (module_utils/front/fleet_api.py) over real sockets: the login service says who
calls (a session or a token), a host's status endpoint stands behind, and the API answers what the
fleet, a host, an instance and its journal are, to whom."""

from __future__ import annotations

import http.client
import json
import re
import socket
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.front import door_auth, fleet_api

HASH = door_auth.hash_password("s3cret", 10000, b"0123456789abcdef")
STATUS = {
    "host": "gpu-1",
    "generated_at": "2026-11-28T14:00:26Z",
    "deployed": True,
    "error": None,
    "instances": [
        {"id": 0, "name": "isaac-sim-0", "configured": True, "state": "ready", "ready": True, "release": "6.x",
         "image": "nvcr.io/nvidia/isaac-sim:6.0.1", "digest": "sha256:" + "a" * 64, "ports": {"signal": 49100},
         "urls": {"signal": "10.0.0.5:49100"}, "lent_to": None, "restarts": 0},
        {"id": 1, "name": "isaac-sim-1", "configured": True, "state": "starting", "ready": False, "release": "6.x",
         "urls": {"signal": "10.0.0.5:49101"}, "lent_to": "nightly-7"},
    ],
}  # fmt: skip


def serve(handler_class):
    server = ThreadingHTTPServer(("127.0.0.1", 0), handler_class)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    return server


class HostStatus(BaseHTTPRequestHandler):
    reads = 0

    def do_GET(self):  # noqa: N802
        if self.path == "/status":
            HostStatus.reads += 1
            body, kind = json.dumps(STATUS).encode(), "application/json"
        elif self.path == "/logs/1?follow=1":
            self.send_response(200)
            self.send_header("Content-Type", "text/plain")
            self.end_headers()
            for i in range(600):
                try:
                    self.wfile.write(f"new {i}\n".encode())
                    self.wfile.flush()
                except OSError:
                    return
                time.sleep(0.1)
            return
        elif self.path == "/logs/1":
            body, kind = "".join(f"line {i}\n" for i in range(300)).encode(), "text/plain"
        else:
            self.send_response(404)
            self.end_headers()
            return
        self.send_response(200)
        self.send_header("Content-Type", kind)
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def log_message(self, *args):
        pass


@pytest.fixture
def api(tmp_path):
    (tmp_path / "users.json").write_text(
        json.dumps({"olga": {"role": "operator", "hash": HASH}, "vic": {"role": "viewer", "hash": HASH}})
    )
    door = door_auth.Door(str(tmp_path / "users.json"), str(tmp_path / "door.db"), 1, log=lambda line: None)
    auth = serve(door_auth.handler(door))
    host = serve(HostStatus)
    config = {
        "door": "https://fleet.lab/",
        "entrances": {"gpu-1": {"0": "https://fleet.lab/viewers/gpu-1/0/"}},
        "hosts": [
            {"name": "gpu-1", "status_url": f"http://127.0.0.1:{host.server_address[1]}/status"},
            {"name": "gpu-2", "status_url": "http://127.0.0.1:9/status"},
        ],
        "session_hours": 8,
    }
    lines = []
    auth_url = f"http://127.0.0.1:{auth.server_address[1]}"
    service = fleet_api.Api(
        fleet_api.Fleet(config, ttl=60, timeout=2),
        lambda cookie, authorization: fleet_api.ask_identity(auth_url, cookie, authorization),
        log=lines.append,
        recheck=0.5,
    )
    server = serve(fleet_api.handler(service))
    operator = f"{door_auth.COOKIE}=" + door.login("olga", "s3cret", "x")
    viewer = f"{door_auth.COOKIE}=" + door.login("vic", "s3cret", "x")
    yield server.server_address[1], door, operator, viewer, lines
    for s in (server, auth, host):
        s.shutdown()
        s.server_close()


def call(port, path, cookie="", token="", method="GET"):
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    headers = {**({"Cookie": cookie} if cookie else {}), **({"Authorization": f"Bearer {token}"} if token else {})}
    conn.request(method, path, headers=headers)
    response = conn.getresponse()
    body = response.read()
    conn.close()
    return response.status, response.getheader("Content-Type"), body


def test_the_fleet_is_read_by_a_session_or_a_token_and_direct_addresses_go_to_operators(api):
    port, door, operator, viewer, _lines = api
    assert call(port, "/api/fleet")[0] == 401
    status, kind, body = call(port, "/api/fleet", viewer)
    assert status == 200 and kind == "application/json"
    fleet = json.loads(body)
    first, second = fleet["hosts"]
    assert (first["name"], first["reachable"], second["name"], second["reachable"]) == ("gpu-1", True, "gpu-2", False)
    assert second["error"].startswith("ConnectionRefusedError") and second["instances"] == []
    ready, starting = first["instances"]
    assert ready["entrance"] == "https://fleet.lab/viewers/gpu-1/0/" and ready["ready"] and ready["holder"] is None
    assert starting["holder"] == {"kind": "test_run", "id": "nightly-7"} and starting["entrance"] is None
    assert "urls" not in ready
    token, _r = door.store.make_token("olga", "ci", ["read"], 1, HASH)
    by_token = json.loads(call(port, "/api/fleet", token=token)[2])
    assert by_token["user"] == "olga" and by_token["hosts"][0]["instances"][0]["urls"] == {"signal": "10.0.0.5:49100"}
    # one read of the host however many ask within ttl
    assert HostStatus.reads == 1
    status, _k, body = call(port, "/api/hosts/gpu-1/instances/1", operator)
    assert status == 200 and json.loads(body)["name"] == "isaac-sim-1"
    assert call(port, "/api/hosts/gpu-1", viewer)[0] == 200
    assert call(port, "/api/hosts/gpu-9", viewer)[0] == 404
    assert call(port, "/api/hosts/gpu-1/instances/7", viewer)[0] == 404
    # a token that may not read reads nothing
    acting, _r = door.store.make_token("olga", "act-only", ["act"], 1, HASH)
    assert call(port, "/api/fleet", token=acting)[0] == 403


def test_the_journal_is_an_operator_s_and_the_tail_is_bounded(api):
    port, _door, operator, viewer, lines = api
    assert call(port, "/api/hosts/gpu-1/instances/1/logs", viewer)[0] == 403
    assert lines[-1] == "refused user=vic path='/api/hosts/gpu-1/instances/1/logs' from=127.0.0.1 (role viewer)"
    status, kind, body = call(port, "/api/hosts/gpu-1/instances/1/logs?tail=3", operator)
    assert status == 200 and kind.startswith("text/plain") and body == b"line 297\nline 298\nline 299\n"
    assert len(call(port, "/api/hosts/gpu-1/instances/1/logs", operator)[2].splitlines()) == 200
    for bad in ("0", "201", "x"):
        assert call(port, f"/api/hosts/gpu-1/instances/1/logs?tail={bad}", operator)[0] == 400, bad
    status, _k, body = call(port, "/api/hosts/gpu-2/instances/0/logs", operator)
    assert status == 404  # an unreachable host has no instance to read


def test_health_and_the_description_need_no_login_and_nothing_else_is_there(api):
    port, _door, operator, _viewer, _lines = api
    assert json.loads(call(port, "/api/health")[2]) == {"status": "ok", "version": fleet_api.VERSION}
    doc = json.loads(call(port, "/api/openapi.json")[2])
    assert doc["openapi"] == "3.0.3" and "/api/hosts/{host}/instances/{n}/logs" in doc["paths"]
    # every route the service answers is in the document, and each documented path answers
    example = {"{host}": "gpu-1", "{n}": "2", "{id}": "0123456789abcdef", "{sid}": "0123456789ab"}
    answered = set()
    for path, methods in doc["paths"].items():
        concrete = path
        for name, value in example.items():
            concrete = concrete.replace(name, value)
        [route] = [r for r, rx in fleet_api._ROUTES if rx.match(concrete)]
        for method in methods:
            assert method.upper() in fleet_api.METHODS.get(route, ("GET",)), (path, method)
            answered.add((route, method.upper()))
    assert answered == {(r, m) for r, _rx in fleet_api._ROUTES for m in fleet_api.METHODS.get(r, ("GET",))}
    assert {"/api/hosts/{host}/instances/{n}/restart", "/api/hosts/{host}/drain"} <= set(doc["paths"])
    status, kind, page = call(port, "/api/docs")
    assert status == 200 and kind.startswith("text/html") and b"GET /api/fleet" in page and b"<script" not in page
    assert call(port, "/api/nothing", operator)[0] == 404
    assert call(port, "/api/fleet", operator, method="POST")[0] == 405
    config = json.loads(call(port, "/api/config", operator)[2])
    assert config["hosts"] == ["gpu-1", "gpu-2"] and "status_urls" in config and "users" not in config


def test_a_followed_journal_streams_until_the_token_reading_it_is_revoked(api):
    port, door, _operator, viewer, lines = api
    token, _r = door.store.make_token("olga", "tail", ["read"], 1, HASH)
    with socket.create_connection(("127.0.0.1", port), timeout=10) as client:
        request = f"GET /api/hosts/gpu-1/instances/1/logs?follow=1 HTTP/1.0\r\nAuthorization: Bearer {token}\r\n\r\n"
        client.sendall(request.encode())
        got = b""
        while got.count(b"new ") < 3:
            got += client.recv(4096)
        assert got.startswith(b"HTTP/1.0 200 ") and b"new 0\nnew 1\n" in got and b"X-Accel-Buffering: no" in got
        assert door.store.revoke("olga", "tail")
        revoked = time.monotonic()
        while chunk := client.recv(4096):
            got += chunk
        # ended at the next check (every 0.5 s here, 3 s on a door), said in the stream and the journal
        assert time.monotonic() - revoked < 3
        assert got.endswith(b"[the session or token ended: the journal stops here]\n")
    assert "follow user=olga token=tail path='/api/hosts/gpu-1/instances/1/logs' from=127.0.0.1" in lines
    assert any(line.endswith("(access ended)") for line in lines), lines
    # a viewer follows nothing
    assert call(port, "/api/hosts/gpu-1/instances/1/logs?follow=1", viewer)[0] == 403


class Garbage(BaseHTTPRequestHandler):
    """A host that answers what is no HTTP, or trickles its answer."""

    def handle(self):
        line = self.rfile.readline()
        if b"trickle" in self.server.kind:
            self.wfile.write(b"HTTP/1.0 200 OK\r\nContent-Length: 100\r\n\r\n")
            for _n in range(100):
                try:
                    self.wfile.write(b" ")
                    self.wfile.flush()
                except OSError:
                    return
                time.sleep(0.1)
        elif line:
            self.wfile.write(b"SPEAKING NO HTTP\r\n\r\n")


@pytest.mark.parametrize("kind", [b"garbage", b"trickle"])
def test_a_host_that_answers_badly_or_slowly_is_one_unreachable_host(kind):
    bad = ThreadingHTTPServer(("127.0.0.1", 0), Garbage)
    bad.kind = kind
    threading.Thread(target=bad.serve_forever, daemon=True).start()
    good = serve(HostStatus)
    fleet = fleet_api.Fleet(
        {
            "hosts": [
                {"name": "bad", "status_url": f"http://127.0.0.1:{bad.server_address[1]}/status"},
                {"name": "gpu-1", "status_url": f"http://127.0.0.1:{good.server_address[1]}/status"},
            ]
        },
        timeout=1,
    )
    try:
        began = time.monotonic()
        first, second = fleet.hosts()
        # the whole answer within the timeout, however it trickles (not 1 s per read)
        assert time.monotonic() - began < 2.5
        assert (first["reachable"], second["reachable"]) == (False, True), first
        assert first["error"].startswith("OSError"), first["error"]
    finally:
        for s in (bad, good):
            s.shutdown()
            s.server_close()


def test_the_api_s_removal_mode_serves_nothing_and_prints_what_it_ended(tmp_path, capsys):
    config = tmp_path / "api.json"
    config.write_text(json.dumps({"hosts": [], "entrances": {}}))
    with pytest.raises(SystemExit):
        fleet_api.main(["--config", str(config)])  # serving needs its port and the login service
    with pytest.raises(SystemExit):
        fleet_api.main(["--config", str(config), "--end-sessions", "gone"])  # and ending needs the store
    capsys.readouterr()
    fleet_api.main(["--config", str(config), "--store", str(tmp_path / "door.db"), "--end-sessions", "gone",
                    "--agent-tls", str(tmp_path / "none")])  # fmt: skip
    assert json.loads(capsys.readouterr().out.splitlines()[-1]) == {"ended": 0, "left": 0, "unfinished": []}


def test_a_read_that_waited_for_a_slow_host_is_fresh_from_its_end_not_its_start():
    now, asked = [0.0], []

    def slow(url):
        asked.append(url)
        now[0] += 5.0  # a host that does not answer holds the read for the whole timeout
        raise OSError("timed out")

    fleet = fleet_api.Fleet({"hosts": [{"name": "gone", "status_url": "http://gone/status"}]}, ttl=2.0,
                            fetch=slow, clock=lambda: now[0])  # fmt: skip
    assert fleet.hosts()[0]["reachable"] is False
    # a caller that waited for that read gets it, and does not wait for another
    assert fleet.hosts()[0]["reachable"] is False and len(asked) == 1
    now[0] += 2.0
    fleet.hosts()
    for _wait in range(100):
        if len(asked) == 2:
            break
        time.sleep(0.01)
    assert len(asked) == 2


class Frozen:
    """Status answers by host name; a frozen host holds each read until it is thawed."""

    def __init__(self):
        self.thawed, self.frozen, self.asked = threading.Event(), set(), []

    def __call__(self, url):
        name = url.split("/")[2]
        self.asked.append(name)
        if name in self.frozen:
            self.thawed.wait(10)
            raise OSError(f"{name}: timed out")
        return json.dumps({"instances": [{"id": 0, "configured": True, "ready": True}]}).encode()


def read_ended(fleet, name):
    """Waits until no read of the host is under way."""
    for _wait in range(500):
        if name not in fleet._asking:  # pylint: disable=protected-access
            return
        time.sleep(0.01)
    raise AssertionError(f"the read of {name} never ended")


def test_a_host_that_stops_answering_holds_a_request_at_most_the_wait_and_the_others_stay_fresh():
    frozen = Frozen()
    hosts = [{"name": n, "status_url": f"http://{n}/status"} for n in ("gpu-1", "gpu-2", "gpu-3")]
    # a wait well above what a loaded machine adds to a request that does not wait (CI runs these beside others)
    fleet = fleet_api.Fleet({"hosts": hosts}, ttl=0.2, wait=2.0, fetch=frozen)
    try:
        assert [h["reachable"] for h in fleet.hosts()] == [True, True, True]
        frozen.frozen.add("gpu-2")
        time.sleep(0.25)  # past the ttl: the next request asks every host again
        began = time.monotonic()
        reads = fleet.hosts()
        took = time.monotonic() - began
        # reported within the wait, not the timeout; the others were read afresh meanwhile
        assert 1.9 <= took < 5, took
        assert [h["reachable"] for h in reads] == [True, False, True]
        assert re.fullmatch(r"TimeoutError: no answer within [1-5]\.\d s \(still asking\)", reads[1]["error"]), reads[1]
        # while that read still hangs, a request neither waits for it nor asks it again; the others are
        # asked again once past the ttl
        time.sleep(0.25)
        asked = len(frozen.asked)
        began = time.monotonic()
        reads = fleet.hosts()
        assert time.monotonic() - began < 1.5
        assert [h["reachable"] for h in reads] == [True, False, True]
        assert sorted(frozen.asked[asked:]) == ["gpu-1", "gpu-3"]
        # its read fails at last: later requests are answered from that failure at once while it is asked again
        frozen.thawed.set()
        read_ended(fleet, "gpu-2")
        frozen.thawed.clear()
        time.sleep(0.25)
        began = time.monotonic()
        reads = fleet.hosts()
        assert time.monotonic() - began < 1.5
        assert reads[1]["error"] == "OSError: gpu-2: timed out"
        # it answers again: the request that sees its failure asks it again (without waiting for it), and
        # the answer is there for the next one at the latest
        frozen.frozen.clear()
        frozen.thawed.set()
        read_ended(fleet, "gpu-2")
        time.sleep(0.25)
        fleet.hosts()
        read_ended(fleet, "gpu-2")
        assert [h["reachable"] for h in fleet.hosts()] == [True, True, True]
    finally:
        frozen.thawed.set()


def test_a_refresh_is_not_answered_by_a_read_that_began_before_it():
    # a read under way across the refresh (its answer may predate the change) is not taken for one after it
    held, answers = threading.Event(), iter([b'{"deployed": "old"}', b'{"deployed": "new"}'])

    def fetch(url):
        held.wait(10)
        return next(answers)

    fleet = fleet_api.Fleet({"hosts": [{"name": "gpu-1", "status_url": "http://gpu-1/status"}]}, ttl=60, wait=5,
                            fetch=fetch)  # fmt: skip
    first = []
    asking = threading.Thread(target=lambda: first.append(fleet.hosts()[0]))
    asking.start()
    for _wait in range(100):
        if "gpu-1" in fleet._asking:  # pylint: disable=protected-access
            break
        time.sleep(0.01)
    fleet.refresh()
    held.set()
    asking.join(10)
    assert first[0]["status"]["deployed"] in ("old", "new")
    assert fleet.hosts()[0]["status"]["deployed"] == "new"


@pytest.mark.filterwarnings("ignore::pytest.PytestUnhandledThreadExceptionWarning")
def test_a_host_is_asked_again_whatever_became_of_its_last_read():
    calls = []

    def fetch(url):
        calls.append(url)
        if len(calls) == 1:
            raise KeyboardInterrupt  # escapes the read's own handling of errors
        return b'{"instances": []}'

    fleet = fleet_api.Fleet({"hosts": [{"name": "gpu-1", "status_url": "http://gpu-1/status"}]}, ttl=0, wait=1,
                            fetch=fetch)  # fmt: skip
    # the read that broke is not left "still asking": the same request asks again, and gets the answer
    assert fleet.hosts()[0]["reachable"] is True and len(calls) == 2
    for reader in [t for t in threading.enumerate() if t.name == "read gpu-1"]:
        reader.join(5)  # its exception reported within this test


def test_a_refresh_is_not_answered_by_a_read_made_within_the_ttl_before_it():
    now = [0.0]
    answers = iter([b'{"instances": [], "deployed": "old"}', b'{"instances": [], "deployed": "new"}'])
    fleet = fleet_api.Fleet({"hosts": [{"name": "gpu-1", "status_url": "http://gpu-1/status"}]}, ttl=60,
                            fetch=lambda url: next(answers), clock=lambda: now[0])  # fmt: skip
    assert fleet.hosts()[0]["status"]["deployed"] == "old"
    now[0] += 1
    assert fleet.hosts()[0]["status"]["deployed"] == "old"  # within the ttl
    fleet.refresh()
    now[0] += 1
    assert fleet.hosts()[0]["status"]["deployed"] == "new"
