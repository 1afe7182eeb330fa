"""Actions through the fleet's API (module_utils/front/fleet_api.py), end to end over real sockets:
the login service says who calls, the API checks scopes, the browser's origin and CSRF token, the
body and the rate, then asks the host's action agent (module_utils/instance/agent.py) over mutual
TLS with the door's client certificate; the agent runs the lifecycle on a scripted host."""

from __future__ import annotations

import contextlib
import http.client
import json
import os
import socket
import threading
import time
import urllib.parse
from http.server import BaseHTTPRequestHandler

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.front import door_auth, fleet_api
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import agent, runlock
from ansible_collections.isaacsim.fleet.tests.unit.helpers import make_pki
from ansible_collections.isaacsim.fleet.tests.unit.plugins.module_utils.front.test_fleet_api import (
    HASH,
    HostStatus,
    serve,
)
from ansible_collections.isaacsim.fleet.tests.unit.plugins.module_utils.instance.test_lifecycle import ScriptedHost

ORIGIN = "https://fleet.lab"


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    return make_pki(tmp_path_factory.mktemp("pki"), agent.CLIENT_NAME)


class Door:
    """The API with its login service, one host's status endpoint and its agent, and a silent host."""

    def __init__(self, tmp_path, pki, per_minute=30):
        (tmp_path / "users.json").write_text(
            json.dumps({"olga": {"role": "operator", "hash": HASH}, "vic": {"role": "viewer", "hash": HASH}})
        )
        self.door = door_auth.Door(str(tmp_path / "users.json"), str(tmp_path / "door.db"), 1, log=lambda line: None)
        self.servers = [serve(door_auth.handler(self.door)), serve(HostStatus)]
        self.scripted = ScriptedHost(4)
        self.scripted.host.wall = time.time
        self.agent_lines = []
        self.agent = agent.Agent(
            "gpu-1",
            str(tmp_path / "agent"),
            host=lambda: self.scripted.host,
            lock=str(tmp_path / "lock.json"),
            record=str(tmp_path / "record.json"),
            drained=str(tmp_path / "drained.json"),
            journal=lambda line, unit="": self.agent_lines.append((unit, line)),
            renew_s=0.05,
        )
        ctx = agent.tls_context(str(pki / "agent.crt"), str(pki / "agent.key"), str(pki / "ca.crt"))
        channel = agent.Server(
            ("127.0.0.1", 0), agent.handler(self.agent), ctx, [agent.ipaddress.ip_network("127.0.0.0/8")],
            log=lambda line: None,
        )  # fmt: skip
        threading.Thread(target=channel.serve_forever, daemon=True).start()
        self.servers.append(channel)
        # a host whose agent port takes connections and never answers
        self.silent = socket.socket()
        self.silent.bind(("127.0.0.1", 0))
        self.silent.listen(8)
        auth, status = self.servers[0].server_address[1], self.servers[1].server_address[1]
        config = {
            "door": ORIGIN + "/",
            "hosts": [
                {"name": "gpu-1", "status_url": f"http://127.0.0.1:{status}/status",
                 "agent_url": f"https://127.0.0.1:{channel.server_address[1]}"},
                {"name": "gpu-2", "status_url": f"http://127.0.0.1:{status}/status",
                 "agent_url": f"https://127.0.0.1:{self.silent.getsockname()[1]}"},
                {"name": "gpu-3", "status_url": f"http://127.0.0.1:{status}/status", "agent_url": ""},
            ],
            "session_hours": 8,
        }  # fmt: skip
        tls = {"ca": str(pki / "ca.crt"), "cert": str(pki / f"{agent.CLIENT_NAME}.crt"),
               "key": str(pki / f"{agent.CLIENT_NAME}.key")}  # fmt: skip
        self.lines = []
        self.agents_config = config
        service = fleet_api.Api(
            fleet_api.Fleet(config, ttl=60, timeout=2),
            lambda cookie, authorization: fleet_api.ask_identity(f"http://127.0.0.1:{auth}", cookie, authorization),
            log=self.lines.append,
            recheck=0.5,
            agents=fleet_api.Agents(config, tls, timeout=1.5),
            limiter=fleet_api.Limiter(per_minute),
        )
        self.servers.append(serve(fleet_api.handler(service)))
        self.port = self.servers[-1].server_address[1]
        self.secret = self.door.login("olga", "s3cret", "x")
        self.operator = f"{door_auth.COOKIE}={self.secret}"
        self.viewer = f"{door_auth.COOKIE}=" + self.door.login("vic", "s3cret", "x")

    def token(self, name, scopes, user="olga"):
        return self.door.store.make_token(user, name, scopes, 1, HASH)[0]

    def close(self):
        for s in self.servers:
            s.shutdown()
            s.server_close()
        self.silent.close()


@pytest.fixture
def door(tmp_path, pki):
    d = Door(tmp_path, pki)
    yield d
    d.close()


def call(port, path, method="POST", token="", cookie="", body=None, headers=None, raw=None):
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=15)
    sent = dict(headers or {})
    if token:
        sent["Authorization"] = f"Bearer {token}"
    if cookie:
        sent["Cookie"] = cookie
    data = raw if raw is not None else (json.dumps(body).encode() if body is not None else None)
    conn.request(method, path, body=data, headers=sent)
    response = conn.getresponse()
    out = response.read()
    conn.close()
    try:
        return response.status, json.loads(out)
    except ValueError:
        return response.status, out


def test_a_token_restarts_an_instance_and_follows_its_progress_to_the_end(door):
    token = door.token("ci", ["read", "act"])
    code, answer = call(door.port, "/api/hosts/gpu-1/instances/2/restart", token=token)
    assert code == 202, answer
    assert answer["state"] == "accepted" and answer["user"] == "olga" and answer["token"] == "ci"
    assert answer["url"] == f"/api/hosts/gpu-1/actions/{answer['id']}" and answer["events"].endswith("?follow=1")
    code, stream = call(door.port, answer["events"], "GET", token=token)
    events = [json.loads(line) for line in stream.decode().splitlines()]
    assert code == 200 and events[0]["text"] == "accepted: restart isaac-sim-2 by olga (token ci)"
    assert events[-1]["state"] == "succeeded" and events[-1]["progress"] == 100
    assert door.scripted.commands("restart") == ["systemctl restart isaac-sim@2.service"]
    code, rec = call(door.port, answer["url"], "GET", token=token)
    assert code == 200 and rec["state"] == "succeeded"
    code, recent = call(door.port, "/api/hosts/gpu-1/actions", "GET", token=token)
    assert [a["id"] for a in recent["actions"]] == [answer["id"]]
    # written down at the door (who, what, the answer) and on the host (in the instance's journal)
    assert any(
        line.startswith("action user=olga token=ci restart gpu-1/2 from=") and line.endswith(f": 202 {answer['id']}")
        for line in door.lines
    )
    assert door.agent_lines[-1][0] == "isaac-sim@2.service"


def test_who_may_act_is_the_role_and_the_token_s_scopes(door):
    assert call(door.port, "/api/hosts/gpu-1/instances/2/restart")[0] == 401
    assert call(door.port, "/api/hosts/gpu-1/instances/2/restart", cookie=door.viewer)[0] == 403
    reader = door.token("reader", ["read"])
    code, answer = call(door.port, "/api/hosts/gpu-1/instances/2/restart", token=reader)
    assert code == 403 and answer["error"] == "restart needs a token with the act scope"
    actor = door.token("actor", ["read", "act"])
    code, answer = call(door.port, "/api/hosts/gpu-1/instances/3", "DELETE", token=actor)
    assert code == 403 and answer["error"] == "remove needs a token with the operate scope"
    assert call(door.port, "/api/hosts/gpu-1/drain", token=actor)[0] == 403
    code, answer = call(door.port, "/api/hosts/gpu-1/instances/2/restart", token=actor, body={"confirm": True})
    assert code == 403 and "operate scope" in answer["error"]
    assert not door.scripted.commands("restart") and not door.scripted.commands("stop")


def test_a_browser_write_needs_the_door_s_own_page_and_the_session_s_csrf_token(door):
    path = "/api/hosts/gpu-1/instances/2/restart"
    code, me = call(door.port, "/session", "GET")  # not the API's: the login service gives it
    csrf = door_auth.csrf_token(door.secret)
    own = {"Origin": ORIGIN, "X-Fleet-Origin": ORIGIN}
    assert call(door.port, path, cookie=door.operator, headers=own)[0] == 403
    assert call(door.port, path, cookie=door.operator, headers={**own, "X-Fleet-CSRF": "0" * 32})[0] == 403
    evil = {"Origin": "https://evil.example", "X-Fleet-Origin": ORIGIN, "X-Fleet-CSRF": csrf}
    assert call(door.port, path, cookie=door.operator, headers=evil)[0] == 403
    sneaky = {**own, "Sec-Fetch-Site": "cross-site", "X-Fleet-CSRF": csrf}
    assert call(door.port, path, cookie=door.operator, headers=sneaky)[0] == 403
    assert not door.scripted.commands("restart")
    code, answer = call(door.port, path, cookie=door.operator, headers={**own, "X-Fleet-CSRF": csrf})
    assert code == 202, answer
    door.agent.wait()
    # the session's token is what the login service says of the session, and ends with it
    assert door.door.whoami(door.operator)[1]["csrf"] == csrf
    door.door.logout(door.operator, "x")
    assert call(door.port, path, cookie=door.operator, headers={**own, "X-Fleet-CSRF": csrf})[0] == 401


@pytest.mark.parametrize(
    ("raw", "code", "words"),
    [
        (b'{"confirm": true, "force": 1}', 400, "force: not a field of an action"),
        (b"{nope", 400, "not JSON"),
        (b"[]", 400, "not a JSON object"),
        (b'{"confirm": "yes"}', 400, "confirm: 'yes' is not true or false"),
        (b'{"confirm": ' + b" " * 5000 + b"false}", 413, "not 0-4096 bytes"),
    ],
)
def test_a_bad_body_is_refused_naming_its_field_and_nothing_runs(door, raw, code, words):
    token = door.token("ops", ["read", "act", "operate"])
    got, answer = call(door.port, "/api/hosts/gpu-1/instances/2/restart", token=token, raw=raw)
    assert got == code and words in answer["error"]
    assert not door.scripted.commands("restart")


def test_unknown_hosts_and_instances_are_404_naming_them_and_wrong_methods_405(door):
    token = door.token("ops", ["read", "act", "operate"])
    code, answer = call(door.port, "/api/hosts/gpu-9/instances/2/restart", token=token)
    assert code == 404 and answer["error"] == "no host gpu-9 behind this front door"
    code, answer = call(door.port, "/api/hosts/gpu-1/instances/7/restart", token=token)
    assert code == 404 and answer["error"].startswith("ids: isaac-sim-7 not on gpu-1")
    assert call(door.port, "/api/hosts/gpu-1/instances/2/restart", "GET", token=token)[0] == 405
    assert call(door.port, "/api/fleet", "POST", token=token)[0] == 405
    assert call(door.port, "/api/hosts/gpu-1/actions/0123456789abcdef", "GET", token=token)[0] == 404
    code, answer = call(door.port, "/api/hosts/gpu-3/instances/0/restart", token=token)
    assert code == 409 and "isaac_sim_agent_enabled: true" in answer["error"]


def test_a_host_held_by_a_deploy_refuses_naming_it_and_n_minus_1_asks_for_a_confirmation(door):
    token = door.token("ops", ["read", "act", "operate"])
    deploy = {"id": "ctl:1:2", "user": "bob", "controller": "ctl", "pid": 1, "started": "2", "play": "Deploy"}
    runlock.acquire(deploy, time.time(), 3600, path=door.agent.lock, guard=door.agent.guard, record_path="")
    code, answer = call(door.port, "/api/hosts/gpu-1/instances/2/restart", token=token)
    assert code == 409 and "bob on ctl (ansible-playbook pid 1, play 'Deploy')" in answer["error"]
    runlock.release(deploy, door.agent.lock, door.agent.guard)
    code, answer = call(door.port, "/api/hosts/gpu-1/instances/1/stop", token=token)
    assert code == 202
    door.agent.wait()
    code, answer = call(door.port, "/api/hosts/gpu-1/instances/2/restart", token=token)
    assert code == 412 and answer["needs_confirm"] and "below N-1 = 3" in answer["error"]
    code, answer = call(door.port, "/api/hosts/gpu-1/instances/2/restart", token=token, body={"confirm": True})
    assert code == 202 and answer["confirmed"]
    door.agent.wait()


def test_drain_and_undrain_through_the_api(door):
    token = door.token("ops", ["read", "act", "operate"])
    code, answer = call(door.port, "/api/hosts/gpu-1/drain", token=token)
    assert code == 200 and answer["state"] == "succeeded" and door.agent.drained_by()["by"] == "olga (token ops)"
    assert call(door.port, "/api/hosts/gpu-1/undrain", token=token)[0] == 200
    assert door.agent.drained_by() is None


def test_cleanup_is_an_operator_s_and_always_asks_first(door):
    actor = door.token("actor", ["read", "act"])
    code, answer = call(door.port, "/api/hosts/gpu-1/cleanup", token=actor, body={"confirm": True})
    assert code == 403 and answer["error"] == "cleanup needs a token with the operate scope"
    token = door.token("ops", ["read", "act", "operate"])
    code, answer = call(door.port, "/api/hosts/gpu-1/cleanup", token=token)
    assert code == 412 and answer["needs_confirm"] and "cleanup removes every instance of gpu-1" in answer["error"]
    assert not door.scripted.commands("stop")
    code, answer = call(door.port, "/api/hosts/gpu-1/cleanup", token=token, body={"confirm": True})
    assert code == 202 and answer["url"] == f"/api/hosts/gpu-1/actions/{answer['id']}"
    door.agent.wait()
    assert door.agent.get(answer["id"])["state"] == "succeeded"
    assert all(u["UnitFileState"] == "disabled" for u in door.scripted.units.values())


def test_a_host_that_does_not_answer_is_reported_in_seconds_and_the_others_still_act(door):
    token = door.token("ops", ["read", "act", "operate"])
    began = time.monotonic()
    code, answer = call(door.port, "/api/hosts/gpu-2/instances/0/restart", token=token)
    took = time.monotonic() - began
    assert code == 504 and answer["error"].startswith("gpu-2's agent did not answer: ")
    assert "The action may have been taken: see /api/hosts/gpu-2/actions" in answer["error"]
    assert took < 5
    assert call(door.port, "/api/hosts/gpu-1/instances/0/restart", token=token)[0] == 202
    door.agent.wait()


def test_a_host_whose_agent_url_leads_to_another_host_s_agent_is_refused_before_any_request(door):
    """The address a host reports could be another host's: the door asks only the agent whose certificate
    the CA issued to that host by name."""
    token = door.token("ops", ["read", "act", "operate"])
    door.agents_config["hosts"][2]["agent_url"] = door.agents_config["hosts"][0]["agent_url"]
    code, answer = call(door.port, "/api/hosts/gpu-3/instances/0/stop", token=token)
    assert code == 504 and "presented the certificate of 'gpu-1 agent', not gpu-3's" in answer["error"]
    assert not door.scripted.commands("stop") and door.agent.recent() == []


def test_odd_bodies_and_headers_are_4xx_never_a_failure(door):
    token = door.token("ops", ["read", "act", "operate"])
    code, answer = call(door.port, "/api/hosts/gpu-1/instances/2/restart", token=token, raw=b"[" * 3000)
    assert code == 400 and "not JSON" in answer["error"]
    own = {"Origin": ORIGIN, "X-Fleet-Origin": ORIGIN, "X-Fleet-CSRF": "\u00e9" * 32}
    conn = http.client.HTTPConnection("127.0.0.1", door.port, timeout=10)
    conn.putrequest("POST", "/api/hosts/gpu-1/instances/2/restart")
    for key, value in {**own, "Cookie": door.operator, "Content-Length": "0"}.items():
        conn.putheader(key, value.encode("utf-8"))
    conn.endheaders()
    assert conn.getresponse().status == 403
    conn.close()
    conn = http.client.HTTPConnection("127.0.0.1", door.port, timeout=10)
    conn.putrequest("POST", "/api/hosts/gpu-1/instances/2/restart")
    conn.putheader("Authorization", f"Bearer {token}")
    conn.putheader("Content-Length", "abc")
    conn.endheaders()
    assert conn.getresponse().status == 413
    conn.close()
    assert not door.scripted.commands("restart")


def test_writes_are_rate_limited_per_token(tmp_path, pki):
    d = Door(tmp_path, pki, per_minute=2)
    try:
        token = d.token("ops", ["read", "act", "operate"])
        assert [call(d.port, "/api/hosts/gpu-1/drain", token=token)[0] for _try in range(3)] == [200, 200, 429]
        # another token of the same person has its own allowance
        other = d.token("ops2", ["read", "act", "operate"])
        assert call(d.port, "/api/hosts/gpu-1/undrain", token=other)[0] == 200
    finally:
        d.close()


class FilesAgent(BaseHTTPRequestHandler):
    """A host agent's /files over its channel, as the pool uses them: GET a holder's stash (its length said,
    or not: read to the connection's end), DELETE it, PUT a tar (a body over 4096 bytes refused at once,
    unread: on its 100-continue, or, for instance 9, as an agent that does not know that header would). A
    holder named session-garbled is answered with what is not HTTP."""

    protocol_version = "HTTP/1.1"
    stash, received = {}, []

    def _send(self, code, body, kind="application/json", length=True):
        data = body if isinstance(body, bytes) else json.dumps(body).encode()
        self.send_response(code)
        self.send_header("Content-Type", kind)
        self.send_header("Connection", "close")
        self.close_connection = True
        if length:
            self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        with contextlib.suppress(OSError):  # the door stopped reading (a body over its limit)
            self.wfile.write(data)

    def _garbled(self):
        if "session-garbled" not in self.path:
            return False
        self.wfile.write(b"nonsense, not HTTP\r\n\r\n")
        self.close_connection = True
        return True

    def do_GET(self):  # noqa: N802
        if self._garbled():
            return None
        holder = urllib.parse.urlsplit(self.path).path.split("/")[2]
        data = self.stash.get(holder)
        if data is None:
            return self._send(404, {"error": f"no files of {holder}"})
        return self._send(200, data, "application/x-tar", length=not holder.startswith("session-unsaid"))

    def do_DELETE(self):  # noqa: N802
        if self._garbled():
            return
        self._send(200, {"removed": self.stash.pop(self.path.split("/")[2], None) is not None})

    def handle_expect_100(self):
        if self._garbled():
            return False
        if "instance=9" in self.path:
            return True  # no 100 Continue, nor a refusal, before the body
        if int(self.headers["Content-Length"]) > 4096:
            self._send(413, {"error": f"{self.headers['Content-Length']} bytes: over 4096"})
            return False
        return super().handle_expect_100()

    def do_PUT(self):  # noqa: N802
        length = int(self.headers["Content-Length"])
        if length > 4096:
            return self._send(413, {"error": f"{length} bytes: over 4096"})
        self.received.append((self.path, self.headers["Content-Type"], self.rfile.read(length)))
        return self._send(200, {"put": 1, "bytes": length})

    def log_message(self, *args):
        pass


@pytest.fixture
def files_agent(pki):
    ctx = agent.tls_context(str(pki / "agent.crt"), str(pki / "agent.key"), str(pki / "ca.crt"))
    server = agent.Server(
        ("127.0.0.1", 0), FilesAgent, ctx, [agent.ipaddress.ip_network("127.0.0.0/8")], log=lambda line: None
    )
    threading.Thread(target=server.serve_forever, daemon=True).start()
    url = f"https://127.0.0.1:{server.server_address[1]}"
    config = {"hosts": [{"name": "gpu-1", "agent_url": url}, {"name": "gpu-3", "agent_url": url}]}
    tls = {"ca": str(pki / "ca.crt"), "cert": str(pki / f"{agent.CLIENT_NAME}.crt"),
           "key": str(pki / f"{agent.CLIENT_NAME}.key")}  # fmt: skip
    FilesAgent.stash, FilesAgent.received = {}, []
    yield fleet_api.Agents(config, tls, timeout=3)
    server.shutdown()
    server.server_close()


def test_a_person_s_files_come_from_the_agent_as_bytes_or_into_a_file_never_past_the_limit(files_agent, tmp_path):
    tar = os.urandom(300_000)
    FilesAgent.stash.update({"session-a": tar, "session-unsaid": tar})
    assert files_agent.fetch("gpu-1", "/files/session-a?max=300000", 300_000) == (200, tar)
    with open(tmp_path / "a.tar", "wb") as fh:
        assert files_agent.fetch("gpu-1", "/files/session-unsaid?max=300000", 300_000, fh) == (200, 300_000)
    assert (tmp_path / "a.tar").read_bytes() == tar
    # over the limit: its length said (nothing read) or not (read to the limit and a byte, no further)
    assert files_agent.fetch("gpu-1", "/files/session-a", 299_999) == (
        413,
        {"error": "300000 bytes, over the limit of 299999", "bytes": 300_000},
    )
    with open(tmp_path / "b.tar", "wb") as fh:
        code, answer = files_agent.fetch("gpu-1", "/files/session-unsaid", 100_000, fh)
    assert (code, answer["bytes"]) == (413, None) and (tmp_path / "b.tar").stat().st_size <= 100_000
    assert files_agent.fetch("gpu-1", "/files/session-b", 10) == (404, {"error": "no files of session-b"})
    assert files_agent.ask("gpu-1", "DELETE", "/files/session-a") == (200, {"removed": True})
    # another host's agent is never asked, whatever address it says it has
    with pytest.raises(OSError, match="presented the certificate of 'gpu-1 agent', not gpu-3's"):
        files_agent.fetch("gpu-3", "/files/session-unsaid", 300_000)


def test_an_agent_that_does_not_answer_in_http_is_an_os_error_for_each_way_of_asking_it(files_agent):
    """The one error the pool catches (it tries again later), whichever call met it."""
    for call_it in (
        lambda: files_agent.ask("gpu-1", "DELETE", "/files/session-garbled"),
        lambda: files_agent.fetch("gpu-1", "/files/session-garbled", 10),
        lambda: files_agent.send("gpu-1", "/files/session-garbled?instance=2", b"x"),
    ):
        with pytest.raises(OSError, match="BadStatusLine"):
            call_it()
    assert FilesAgent.received == []


def test_a_person_s_files_go_to_the_agent_from_bytes_or_a_file_and_a_refusal_comes_before_they_are_sent(
    files_agent, tmp_path, monkeypatch
):
    assert files_agent.send("gpu-1", "/files/session-a?instance=2", b"x" * 4000) == (200, {"put": 1, "bytes": 4000})
    (tmp_path / "a.tar").write_bytes(b"y" * 4096)
    with open(tmp_path / "a.tar", "rb") as fh:
        assert files_agent.send("gpu-1", "/files/session-a?instance=2", fh) == (200, {"put": 1, "bytes": 4096})
    assert FilesAgent.received == [
        ("/files/session-a?instance=2", "application/x-tar", b"x" * 4000),
        ("/files/session-a?instance=2", "application/x-tar", b"y" * 4096),
    ]
    # the agent refuses a tar over its limit without reading it: its answer is what the door gets, on its 100
    # continue or before it (an agent that does not know that header), and no byte of the tar is sent
    (tmp_path / "big.tar").write_bytes(os.urandom(8 * 1024 * 1024))
    for n in (2, 9):
        with open(tmp_path / "big.tar", "rb") as fh:
            code, answer = files_agent.send("gpu-1", f"/files/session-a?instance={n}", fh)
            assert fh.tell() == 0
        assert (code, answer) == (413, {"error": f"{8 * 1024 * 1024} bytes: over 4096"})
    # an agent that says nothing to the header gets the files after CONTINUE_WAIT
    monkeypatch.setattr(fleet_api, "CONTINUE_WAIT", 0.2)
    assert files_agent.send("gpu-1", "/files/session-a?instance=9", b"z" * 10) == (200, {"put": 1, "bytes": 10})
    with pytest.raises(OSError, match="not gpu-3's"):
        files_agent.send("gpu-3", "/files/session-a?instance=2", b"x")
    assert len(FilesAgent.received) == 3
