# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The fleet's API on the front door (isaac-sim-front-door-api.service): JSON over the front
door's HTTPS, behind its login, for people and programs (API tokens).

It reads: the fleet (each host behind the door, its instances with state, readiness, release,
image, ports, entrance and holder), one host, one instance, an instance's journal (operators), the
effective configuration of the door, its health, and its own OpenAPI document and docs page. It
changes nothing yet: actions on instances come through the one lifecycle, on the hosts.

Who asks is never taken from a header: the service asks the login service (/session) with the
request's own cookie or token, as nginx passed them, so a process of the door host that reaches
its port still needs a session. Each host's status endpoint is read over HTTP as the dashboard
reads it, at most once per `ttl` seconds however many ask.

The standard library alone, like the login service (front/door_auth.py): the door host needs no
package from PyPI, and the same code runs on Debian 12's Python 3.11 and 13's 3.13 (Debian's
FastAPI differs between the two: 0.92 with pydantic 1, 0.115 with pydantic 2).
"""

from __future__ import annotations

import contextlib
import hmac
import html
import http.client
import io
import json
import os
import re
import select
import socket
import ssl
import sys
import threading
import time
import urllib.parse
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

try:
    from ansible_collections.isaacsim.fleet.plugins.module_utils.front import pool as sim_pool
except ImportError:  # on the front door host, beside the service's script
    import isaac_sim_door_pool as sim_pool  # type: ignore[no-redef]

VERSION = "1"
MAX_TAIL = 200
# a host's answer: read whole within the timeout, at most this big
MAX_ANSWER = 16 * 1024 * 1024
# a host's status read is waited for at most this long, then the host is reported as not answering while
# the read goes on (up to its timeout): "a host that does not answer is reported within 5 s"
ANSWER_WAIT = 3.0
# a followed journal asks again who is reading this often: a logout or a revoked token ends it within 5 s,
# as it refuses any other request at once
RECHECK_SECONDS = 3
# the scope a token needs for each action (a session holds its role's); confirming an action that takes
# a host below N-1 serving instances needs operate
ACTION_SCOPES = {
    "start": "act",
    "stop": "act",
    "restart": "act",
    "remove": "operate",
    "drain": "operate",
    "undrain": "operate",
    "cleanup": "operate",
}
# the actions on a host as a whole (the others are an instance's)
HOST_ACTIONS = {
    "drain": "no new claim there, what runs goes on",
    "undrain": "claims are taken again",
    "cleanup": "remove every instance of the host through its lifecycle, caches and logs kept (the old web "
    "service's Cleanup All); always asks for confirm: true",
}
_HOST = r"(?P<host>[A-Za-z0-9._-]+)"
# the routes' action names, from the tables above
_INSTANCE_ACTIONS = "|".join(a for a in ACTION_SCOPES if a not in HOST_ACTIONS)
_HOST_ACTIONS = "|".join(HOST_ACTIONS)
_ROUTES = [
    ("health", re.compile(r"^/api/health\Z")),
    ("openapi", re.compile(r"^/api/openapi\.json\Z")),
    ("docs", re.compile(r"^/api/docs\Z")),
    ("fleet", re.compile(r"^/api/fleet\Z")),
    ("config", re.compile(r"^/api/config\Z")),
    ("host", re.compile(rf"^/api/hosts/{_HOST}\Z")),
    ("instance", re.compile(rf"^/api/hosts/{_HOST}/instances/(?P<n>[0-9]{{1,2}})\Z")),
    ("logs", re.compile(rf"^/api/hosts/{_HOST}/instances/(?P<n>[0-9]{{1,2}})/logs\Z")),
    ("act", re.compile(rf"^/api/hosts/{_HOST}/instances/(?P<n>[0-9]{{1,2}})/(?P<action>{_INSTANCE_ACTIONS})\Z")),
    ("host_act", re.compile(rf"^/api/hosts/{_HOST}/(?P<action>{_HOST_ACTIONS})\Z")),
    ("actions", re.compile(rf"^/api/hosts/{_HOST}/actions\Z")),
    ("action", re.compile(rf"^/api/hosts/{_HOST}/actions/(?P<id>[a-f0-9]{{16}})\Z")),
    ("sessions", re.compile(r"^/api/sessions\Z")),
    ("session", re.compile(r"^/api/sessions/(?P<sid>[a-f0-9]{12})\Z")),
]
# what each route needs: nothing (health, the API's own description), a session or token that may
# read, or an operator's
NEEDS = {
    "health": None,
    "openapi": None,
    "docs": None,
    "logs": "operator",
    "act": "operator",
    "host_act": "operator",
    "actions": "operator",
    "action": "operator",
}
# the methods of each route (GET where not named); DELETE of an instance is its remove
METHODS = {
    "act": ("POST",),
    "host_act": ("POST",),
    "instance": ("GET", "DELETE"),
    "sessions": ("GET", "POST"),
    "session": ("GET", "DELETE"),
}
MAX_BODY = 4096
# seconds an action's request may take to be taken (the agent checks the host first)
WRITE_TIMEOUT = 15.0
# a person's files (a tar of Documents) to or from a host's agent: each step of the transfer within
# TRANSFER_TIMEOUT, and the whole within TRANSFER_TIMEOUT plus a second per TRANSFER_RATE bytes (a host
# that trickles its files is cut off)
TRANSFER_TIMEOUT, TRANSFER_RATE = 60.0, 4 * 1024 * 1024
# how long a transfer to an agent waits for its 100 Continue (or its refusal) before it sends the files anyway
CONTINUE_WAIT = 1.0
# what a write's checks read of its request (another_site, the CSRF token)
_WRITE_HEADERS = ("Origin", "X-Fleet-Origin", "Sec-Fetch-Site", "X-Fleet-CSRF")
# writes per minute per person or token (a burst of that many, then one every 60/N s)
WRITES_PER_MINUTE = 30


def instance_view(host: str, inst: dict, entrance, operator: bool) -> dict:
    """An instance as the API gives it: what a person needs to pick one and what holds it. Direct
    addresses (urls) go to operators alone, as on the dashboard."""
    run = inst.get("lent_to")
    view = {
        "host": host,
        "id": inst.get("id"),
        "name": inst.get("name"),
        "state": inst.get("state"),
        "ready": bool(inst.get("ready")),
        "release": inst.get("release"),
        "profile": inst.get("profile"),
        "gpu_model": inst.get("gpu_model"),
        "image": inst.get("image"),
        "digest": inst.get("digest"),
        "ports": inst.get("ports") or {},
        "entrance": entrance,
        # the instance's one claim: a person's session (front/pool.py) or a test run's loan (experience.yml,
        # test_suite.yml)
        "holder": holder(run),
        "health": inst.get("health"),
        "restarts": inst.get("restarts"),
        "uptime_s": inst.get("uptime_s"),
        "down_reason": inst.get("down_reason"),
    }
    if operator:
        view["urls"] = inst.get("urls") or {}
    return view


def holder(lent_to):
    """Who holds an instance, from its host's loan marker: a session or a test run; None: nobody."""
    if not lent_to:
        return None
    session = re.match(r"^session-([a-z0-9]+)\Z", lent_to)
    return {"kind": "session", "id": session.group(1)} if session else {"kind": "test_run", "id": lent_to}


class Fleet:
    """The hosts behind the door and their last status reads, each host's refreshed at most once per ttl.

    Each host is read on its own thread. A request waits for a host's read until `wait` seconds after
    that read began, then reports the host as not answering while the read goes on (up to `timeout`); a
    host whose last read failed is reported from that read at once while it is asked again. One frozen
    host holds no request up longer than `wait`, and the others are served as fresh as ever."""

    def __init__(
        self, config: dict, ttl: float = 2.0, timeout: float = 5.0, fetch=None, clock=time.monotonic, wait=ANSWER_WAIT
    ):
        self.config, self.ttl, self.timeout, self.wait, self.clock = config, ttl, timeout, wait, clock
        self.fetch = fetch or self._fetch
        self._lock = threading.Lock()
        # host name -> its last read {"read", "started", "ended"}; host name -> (Event, time.monotonic() at its
        # start) of its read under way
        self._reads, self._asking = {}, {}
        self._refreshed = float("-inf")

    def _fetch(self, url: str) -> bytes:
        return get(url, self.timeout)

    def _read(self, backend: dict) -> dict:
        try:
            status = json.loads(self.fetch(backend["status_url"]))
            if not isinstance(status, dict):
                raise ValueError("the answer is not a JSON object")
            # each instance's GPU model, as its host's driver names the GPU at the instance's index (a session
            # may ask for one)
            models = {g.get("index"): g.get("name") for g in (status.get("gpu") or {}).get("gpus") or []}
            for inst in status.get("instances") or []:
                inst["gpu_model"] = models.get(inst.get("gpu"))
            return {"name": backend["name"], "reachable": True, "error": status.get("error"), "status": status}
        # whatever one host answers (or not), the others are still served
        except Exception as exc:  # pylint: disable=broad-exception-caught
            return {"name": backend["name"], "reachable": False, "error": f"{type(exc).__name__}: {exc}", "status": {}}

    def _read_into(self, backend: dict, done: threading.Event) -> None:
        started, read = self.clock(), None
        try:
            read = self._read(backend)
        finally:
            # whatever became of the read, the host is asked again next time (else it would stay "still asking")
            with self._lock:
                if read is not None:
                    # fresh from when it ended: a caller that waited for it must not read again
                    self._reads[backend["name"]] = {"read": read, "started": started, "ended": self.clock()}
                self._asking.pop(backend["name"], None)
            done.set()

    def _fresh(self, last, since: float) -> bool:
        """The read will do for a request that began at `since`: made since then, or within the ttl (and
        after the last refresh either way)."""
        if not last or last["started"] < self._refreshed:
            return False
        return last["started"] >= since or self.clock() - last["ended"] < self.ttl

    def _ask(self, backend: dict, since: float):
        """The read of this host to wait for, started when none is under way; None when its last read will do."""
        name, last = backend["name"], self._reads.get(backend["name"])
        if self._fresh(last, since):
            return None
        if name not in self._asking:
            done = threading.Event()
            self._asking[name] = (done, time.monotonic())
            try:
                threading.Thread(target=self._read_into, args=(backend, done), daemon=True, name=f"read {name}").start()
            except BaseException:
                del self._asking[name]
                raise
        done, began = self._asking[name]
        if (last and not last["read"]["reachable"]) or time.monotonic() - began >= self.wait:
            return None
        return done, began + self.wait

    def _answer(self, backend: dict, since: float) -> dict:
        last = self._reads.get(backend["name"])
        if self._fresh(last, since) or (last and not last["read"]["reachable"]):
            return last["read"]
        asking = self._asking.get(backend["name"])
        if asking:
            why = f"TimeoutError: no answer within {time.monotonic() - asking[1]:.1f} s (still asking)"
        else:
            why = f"TimeoutError: no fresh answer within {self.wait:g} s"
        return {"name": backend["name"], "reachable": False, "error": why, "status": {}}

    def hosts(self) -> list:
        backends = self.config.get("hosts") or []
        deadline, since = time.monotonic() + self.wait, self.clock()
        while True:
            with self._lock:
                waiting = [read for read in (self._ask(b, since) for b in backends) if read is not None]
            if not waiting or time.monotonic() >= deadline:
                break
            # a read that began before a refresh() is waited for, then another, all within the request's wait
            for done, until in waiting:
                done.wait(max(0.0, min(until, deadline) - time.monotonic()))
        with self._lock:
            return [self._answer(b, since) for b in backends]

    def refresh(self) -> None:
        """The next read asks the hosts again (something changed there)."""
        with self._lock:
            self._refreshed = self.clock()

    def host_view(self, read: dict, operator: bool) -> dict:
        status = read["status"]
        entrances = (self.config.get("entrances") or {}).get(read["name"]) or {}
        return {
            "name": read["name"],
            "reachable": read["reachable"],
            "error": read["error"],
            "generated_at": status.get("generated_at"),
            "deployed": status.get("deployed"),
            "drained": status.get("drained"),
            "instances": [
                instance_view(read["name"], i, entrances.get(str(i.get("id"))), operator)
                for i in status.get("instances") or []
                if i.get("configured") or i.get("id") is not None
            ],
        }


def openapi() -> dict:
    """The API's OpenAPI 3.0 document."""

    def op(summary, params=(), need="read", extra=None):
        answers = {"200": {"description": "OK"}, "401": {"description": "No session or token"}}
        if need == "operator":
            answers["403"] = {"description": "Not an operator (or the token lacks that scope)"}
        if params:
            answers["404"] = {"description": "No such host or instance"}
        extra = dict(extra or {})
        answers.update({code: {"description": text} for code, text in extra.pop("responses_extra", {}).items()})
        out = {"summary": summary, "responses": answers, "parameters": list(params)}
        if need is None:
            out["security"] = []
        return dict(out, **extra)

    host = {"name": "host", "in": "path", "required": True, "schema": {"type": "string"}}
    n = {"name": "n", "in": "path", "required": True, "schema": {"type": "integer", "minimum": 0, "maximum": 99}}
    tail = {"name": "tail", "in": "query", "schema": {"type": "integer", "minimum": 1, "maximum": MAX_TAIL}}
    follow = {
        "name": "follow",
        "in": "query",
        "description": "1: then each new line as it comes, while the session or token lasts",
        "schema": {"type": "integer", "enum": [1]},
    }
    action_id = {
        "name": "id",
        "in": "path",
        "required": True,
        "schema": {"type": "string", "pattern": "^[a-f0-9]{16}$"},
    }
    session_id = {
        "name": "id",
        "in": "path",
        "required": True,
        "schema": {"type": "string", "pattern": "^[a-f0-9]{12}$"},
    }
    write = {
        "requestBody": {
            "required": False,
            "content": {
                "application/json": {
                    "schema": {
                        "type": "object",
                        "additionalProperties": False,
                        "properties": {
                            "confirm": {
                                "type": "boolean",
                                "description": "go below N-1 serving instances, or clean the host up (operate scope)",
                            }
                        },
                    }
                }
            },
        },
        "responses_extra": {
            "202": "Taken: the action runs on the host",
            "400": "A malformed body (the field is named)",
            "409": "The host is held (a deploy, another action): the holder is named",
            "412": "It would take the host below N-1 serving instances, or it is a cleanup: confirm it",
            "413": "A body over 4096 bytes",
            "429": "Too many actions a minute",
            "504": "The host's agent did not answer",
        },
    }
    return {
        "openapi": "3.0.3",
        "info": {
            "title": "Isaac Sim fleet API",
            "version": VERSION,
            "description": "The fleet behind this front door. Log in (the session cookie) or send an API token "
            "(Authorization: Bearer isf_...).",
        },
        "components": {
            "securitySchemes": {
                "token": {"type": "http", "scheme": "bearer"},
                "session": {"type": "apiKey", "in": "cookie", "name": "__Host-fleet_session"},
            }
        },
        "security": [{"token": []}, {"session": []}],
        "paths": {
            "/api/health": {"get": op("The API answers (no login)", need=None)},
            "/api/openapi.json": {"get": op("This document (no login)", need=None)},
            "/api/docs": {"get": op("This document as a page (no login)", need=None)},
            "/api/fleet": {"get": op("Every host behind the door and its instances")},
            "/api/config": {"get": op("The front door's effective configuration (no secret)")},
            "/api/hosts/{host}": {"get": op("One host and its instances", [host])},
            "/api/hosts/{host}/instances/{n}": {
                "get": op("One instance", [host, n]),
                "delete": op(
                    "Remove the instance (its caches, logs and data stay): as .../remove", [host, n], "operator", write
                ),  # fmt: skip
            },
            **{
                f"/api/hosts/{{host}}/instances/{{n}}/{action}": {
                    "post": op(
                        f"{action.capitalize()} the instance through the host's lifecycle: 202 and the "
                        f"action, then its events (needs the {scope} scope)",
                        [host, n],
                        "operator",
                        write,
                    )
                }
                for action, scope in ACTION_SCOPES.items()
                if action not in HOST_ACTIONS
            },  # fmt: skip
            **{
                f"/api/hosts/{{host}}/{action}": {
                    "post": op(
                        f"{action.capitalize()} the host: {said} (needs the operate scope)",
                        [host],
                        "operator",
                        write,
                    )
                }
                for action, said in HOST_ACTIONS.items()
            },  # fmt: skip
            "/api/sessions": {
                "get": op("Your sessions and places in the queue (operators: everyone's too)"),
                "post": op(
                    "Ask for a simulator (the use scope): 201 and the session where an instance is free, else "
                    "202 and your place in the queue; {} or release, profile (what the instance runs), gpu (the "
                    "model of its GPU, as L40S or NVIDIA L40S)",
                    extra={
                        "responses_extra": {
                            "201": "A session: its instance and entrance",
                            "202": "A place in the queue: look at it (GET) to keep it",
                            "400": "A malformed body (the field is named)",
                            "409": "You have as many sessions as you may",
                        }
                    },
                ),
            },
            "/api/sessions/{sid}": {
                "get": op(
                    "One of your sessions or places: its state, entrance, time left, warning, what became of your "
                    "files (Documents)",
                    [session_id],
                ),
                "delete": op(
                    "End it (the use scope; an operator ends anyone's): its instance is reset, then free",
                    [session_id],
                ),
            },
            "/api/hosts/{host}/actions": {"get": op("The host's last actions (operators)", [host], "operator")},
            "/api/hosts/{host}/actions/{id}": {
                "get": op(
                    "One action: its state, events and outcome; ?follow=1 its events as they come (one JSON "
                    "line each) until it ends (operators)",
                    [host, action_id, follow],
                    "operator",
                )
            },  # fmt: skip
            "/api/hosts/{host}/instances/{n}/logs": {
                "get": op("The instance's last journal lines, as text (operators)", [host, n, tail, follow], "operator")
            },
        },
    }


def docs_page(doc: dict) -> str:
    """The OpenAPI document as a page, server-side: no script, nothing fetched from elsewhere."""
    rows = []
    for path, methods in doc["paths"].items():
        for method, spec in methods.items():
            params = ", ".join(p["name"] for p in spec.get("parameters") or []) or "-"
            login = "no" if spec.get("security") == [] else "yes"
            rows.append(
                f"<tr><td><code>{method.upper()} {html.escape(path)}</code></td><td>{html.escape(spec['summary'])}"
                f"</td><td>{html.escape(params)}</td><td>{login}</td></tr>"
            )
    return (
        '<!doctype html><html lang="en"><head><meta charset="utf-8"><title>Isaac Sim fleet API</title>'
        "<style>body{font-family:system-ui,sans-serif;margin:2em}td,th{padding:.3em .8em;text-align:left}"
        "</style></head><body>"
        f"<h1>{html.escape(doc['info']['title'])}</h1><p>{html.escape(doc['info']['description'])}</p>"
        '<p>The machine-readable document: <a href="/api/openapi.json">/api/openapi.json</a>.</p>'
        "<table><tr><th>Request</th><th>What it gives</th><th>Parameters</th><th>Login</th></tr>"
        + "".join(rows)
        + "</table></body></html>\n"
    )


def get(url: str, timeout: float, headers=None, ok=(200,)) -> bytes:
    """The body of an http:// GET, read whole within timeout seconds altogether (a host that
    trickles its answer is cut off) and at most MAX_ANSWER bytes; OSError for anything else."""
    address = urllib.parse.urlsplit(url)
    deadline = time.monotonic() + timeout
    conn = http.client.HTTPConnection(address.hostname, address.port or 80, timeout=timeout)
    try:
        conn.request("GET", address.path + (f"?{address.query}" if address.query else ""), headers=headers or {})
        answer = conn.getresponse()
        if answer.status not in ok:
            raise OSError(f"HTTP {answer.status}")
        body = b""
        while chunk := answer.read1(65536):
            body += chunk
            if len(body) > MAX_ANSWER:
                raise OSError(f"an answer over {MAX_ANSWER} bytes")
            if time.monotonic() > deadline:
                raise OSError(f"no whole answer within {timeout} s")
        return body
    except http.client.HTTPException as exc:
        raise OSError(f"{type(exc).__name__}: {exc}") from exc
    finally:
        conn.close()


def ask_identity(auth_url: str, cookie: str, authorization: str, timeout: float = 5.0):
    """{user, role, token, scopes} from the login service for these credentials; None without one."""
    headers = {k: v for k, v in (("Cookie", cookie), ("Authorization", authorization)) if v}
    try:
        return json.loads(get(f"{auth_url}/session", timeout, headers, ok=(200,)))
    except OSError as exc:
        if str(exc) == "HTTP 401":
            return None
        raise


def say(line: str) -> None:
    sys.stdout.write(line + "\n")
    sys.stdout.flush()


def drain(client, budget: list) -> bool:
    """Whether a client whose socket is readable is still there: what it sends now (a request's
    body) is read and dropped, so select() does not wake for it again; closed, or over its budget
    (a one-item list of the bytes it may still send), it is gone."""
    try:
        data = client.recv(65536)
    except OSError:
        return False
    budget[0] -= len(data)
    return bool(data) and budget[0] >= 0


class Follow:
    """A stream a host gives until it ends, open and answering 200, to be copied to a client while
    the one who asked may still read it: an instance's followed journal (the status endpoint's
    /logs/N?follow=1) or an action's events (the agent's, over its TLS channel: ctx)."""

    def __init__(self, url: str, path: str, timeout: float = 10.0, ctx=None, check=None):
        """check(sock): raises OSError for a peer that is not the one meant (before a byte is sent)."""
        address = urllib.parse.urlsplit(url)
        self.sock = socket.create_connection((address.hostname, address.port), timeout=timeout)
        try:
            if ctx is not None:
                self.sock = ctx.wrap_socket(self.sock, server_hostname=address.hostname)
            if check is not None:
                check(self.sock)
        except OSError:
            self.sock.close()
            raise
        self.sock.sendall(f"GET {path} HTTP/1.0\r\nHost: {address.netloc}\r\n\r\n".encode())
        head = b""
        while b"\r\n\r\n" not in head and len(head) < 65536:
            chunk = self.sock.recv(4096)
            if not chunk:
                break
            head += chunk
        head, _sep, self.rest = head.partition(b"\r\n\r\n")
        status = head.split(b"\r\n", 1)[0].decode("latin-1")
        if not re.match(r"^HTTP/1\.[01] 200 ", status):
            self.sock.close()
            raise OSError(status or "no answer")
        self.ended = b"\n[the session or token ended: the journal stops here]\n"

    def copy(self, write, client, still_allowed, recheck: float = RECHECK_SECONDS, clock=time.monotonic) -> str:
        """Copies until the host's stream ends, the client goes, or still_allowed() says no (asked
        every recheck seconds); why it ended."""
        why, asked, budget = "host ended", clock(), [65536]
        try:
            if self.rest:
                write(self.rest)
            while True:
                pending = isinstance(self.sock, ssl.SSLSocket) and self.sock.pending()
                ready, _w, _x = select.select([self.sock, client], [], [], 0 if pending else 1.0)
                if pending:
                    ready = [*ready, self.sock]
                if client in ready and not drain(client, budget):
                    return "client gone"
                if self.sock in ready:
                    try:
                        data = self.sock.recv(65536)
                    except ssl.SSLWantReadError:  # a TLS record not whole yet
                        continue
                    if not data:
                        return why
                    write(data)
                if clock() - asked >= recheck:
                    asked = clock()
                    if not still_allowed():
                        write(self.ended)
                        return "access ended"
        except OSError:
            return "client gone"
        finally:
            self.sock.close()


class Agents:
    """The hosts' action agents (module_utils/instance/agent.py), over their channel: TLS with the
    door's client certificate, each host's certificate checked against the collection's CA and the
    address the door reaches it at. tls: {ca, cert, key} files; None: no agent is reachable."""

    def __init__(self, config: dict, tls=None, timeout: float = 5.0):
        self.config, self.timeout, self.ctx = config, timeout, None
        if tls:
            self.ctx = ssl.create_default_context(cafile=tls["ca"])
            self.ctx.minimum_version = ssl.TLSVersion.TLSv1_2
            self.ctx.load_cert_chain(tls["cert"], tls["key"])

    def url(self, host: str) -> str:
        backend = next((b for b in self.config.get("hosts") or [] if b["name"] == host), None) or {}
        return backend.get("agent_url") or "" if self.ctx else ""

    def check(self, host: str, sock) -> None:
        """The peer is this host's agent: a certificate of the CA (TLS checked it, and its address) issued to
        the host by that name, so a host that says another's address is never taken for it."""
        name = peer_name(sock.getpeercert())
        if name != f"{host} agent":
            raise OSError(f"the agent at {self.url(host)} presented the certificate of {name!r}, not {host}'s")

    def _connect(self, host: str) -> http.client.HTTPSConnection:
        """A connection to the host's agent, its certificate checked before a byte is sent."""
        address = urllib.parse.urlsplit(self.url(host))
        conn = http.client.HTTPSConnection(
            address.hostname, address.port, context=self.ctx, timeout=self.timeout, blocksize=65536
        )
        try:
            conn.connect()
            self.check(host, conn.sock)
        except BaseException:
            conn.close()
            raise
        return conn

    @contextlib.contextmanager
    def _talk(self, host: str):
        """A checked connection to the host's agent (_connect), closed after; HTTP's own errors in it raised
        as OSError, the one error its callers catch."""
        try:
            conn = self._connect(host)
            try:
                yield conn
            finally:
                conn.close()
        except http.client.HTTPException as exc:
            raise OSError(f"{type(exc).__name__}: {exc}") from exc

    @staticmethod
    def _read_json(answer) -> tuple:
        text = answer.read(MAX_ANSWER + 1)
        if len(text) > MAX_ANSWER:
            raise OSError(f"an answer over {MAX_ANSWER} bytes")
        try:
            return answer.status, json.loads(text)
        except ValueError as exc:
            raise OSError(f"an answer that is not JSON (HTTP {answer.status})") from exc

    def ask(self, host: str, method: str, path: str, body=None) -> tuple:
        """(status, answer) of the host's agent; OSError when it does not connect within the timeout, or
        (an action, which may take a moment to be taken) answer within WRITE_TIMEOUT."""
        with self._talk(host) as conn:
            if method == "POST":
                conn.sock.settimeout(WRITE_TIMEOUT)
            data = json.dumps(body).encode() if body is not None else None
            conn.request(method, path, body=data, headers={"Content-Type": "application/json"})
            return self._read_json(conn.getresponse())

    def fetch(self, host: str, path: str, max_bytes: int, into=None) -> tuple:
        """(status, answer) of a GET of bytes (a person's files) from the host's agent: 200 and the body
        (bytes), or its length once written into `into` (a binary file); another status and its JSON. A body
        over max_bytes is never read past max_bytes + 1: (413, {error, bytes}) as the agent's own refusal
        gives it (bytes: None where the agent sent no length). OSError as ask(), or for a body that is not
        whole within the transfer's time."""
        with self._talk(host) as conn:
            conn.sock.settimeout(TRANSFER_TIMEOUT)
            conn.request("GET", path)
            answer = conn.getresponse()
            if answer.status != 200:
                return self._read_json(answer)
            return self._body(answer, max_bytes, into)

    @staticmethod
    def _body(answer, max_bytes: int, into) -> tuple:
        """(200, the body or its length written into `into`), or (413, {error, bytes}) over max_bytes."""
        said = answer.getheader("Content-Length")
        if said is not None and not said.isdigit():
            raise OSError(f"a Content-Length that is not a number: {said!r}")
        if said is not None and int(said) > max_bytes:
            return 413, {"error": f"{said} bytes, over the limit of {max_bytes}", "bytes": int(said)}
        deadline, got, parts = time.monotonic() + TRANSFER_TIMEOUT + max_bytes / TRANSFER_RATE, 0, []
        while chunk := answer.read1(min(65536, max_bytes + 1 - got)):
            got += len(chunk)
            if got > max_bytes:
                return 413, {"error": f"more than the limit of {max_bytes} bytes", "bytes": None}
            if time.monotonic() > deadline:
                raise OSError(f"no whole answer within {deadline:.0f} s")
            if into is None:
                parts.append(chunk)
            else:
                into.write(chunk)
        if said is not None and got != int(said):
            raise OSError(f"{got} bytes of {said}: the answer was cut off")
        return 200, (b"".join(parts) if into is None else got)

    def send(self, host: str, path: str, data) -> tuple:
        """(status, JSON answer) of bytes (a tar of a person's files) PUT to the host's agent: data is bytes
        or a binary file, sent from where it stands to its end with its Content-Length. An agent that answers
        before it has read all (a refusal) is not sent the rest: its answer is returned. OSError as ask()."""
        size = len(data) if isinstance(data, (bytes, bytearray)) else os.fstat(data.fileno()).st_size - data.tell()
        # the agent unpacks the files into the instance before it answers
        wait = TRANSFER_TIMEOUT + size / TRANSFER_RATE
        with self._talk(host) as conn:
            conn.putrequest("PUT", path, skip_accept_encoding=True)
            conn.putheader("Content-Type", "application/x-tar")
            conn.putheader("Content-Length", str(size))
            # a refusal (not held, too big) comes before a byte of the files is sent
            conn.putheader("Expect", "100-continue")
            conn.endheaders()
            early = _await_continue(conn.sock, CONTINUE_WAIT)
            if early is None:
                early = _send_body(conn.sock, data, size, time.monotonic() + wait)
            conn.sock.settimeout(wait)
            if early is None:
                return self._read_json(conn.getresponse())
            answer = http.client.HTTPResponse(_Replay(early, conn.sock), method="PUT")
            answer.begin()
            return self._read_json(answer)

    def events(self, host: str, action_id: str, follow):
        """The action's events as they come (a Follow over the channel)."""
        stream = follow(
            self.url(host),
            f"/actions/{action_id}/events?follow=1",
            self.timeout,
            self.ctx,
            lambda s: self.check(host, s),
        )
        stream.ended = b'{"text": "the session or token ended: the events stop here"}\n'
        return stream


def _recv_now(sock):
    """What the socket holds now (b"": the agent closed it); None where it held TLS's own records only (a
    session ticket)."""
    sock.settimeout(0)
    try:
        return sock.recv(65536)
    except (ssl.SSLWantReadError, ssl.SSLWantWriteError, BlockingIOError):
        return None
    finally:
        sock.settimeout(TRANSFER_TIMEOUT)


def _await_continue(sock, wait: float):
    """After the headers of a request that said Expect: 100-continue: None once the agent says go on, or says
    nothing within wait (an agent that does not know the header reads the body anyway); else the bytes of
    its final answer, which came first (a refusal: not a byte of the body is sent)."""
    got, deadline = b"", time.monotonic() + wait
    while True:
        held = isinstance(sock, ssl.SSLSocket) and sock.pending()
        left = deadline - time.monotonic() if not got else TRANSFER_TIMEOUT
        if not held and not select.select([sock], [], [], max(0.0, left))[0]:
            if got:
                raise TimeoutError("a part of an answer, then nothing")
            return None
        chunk = _recv_now(sock)
        if chunk is None:
            continue
        if not chunk:
            raise OSError("the agent closed the connection before the files were sent")
        got += chunk
        if len(got) < 12:  # HTTP/1.1 NNN
            continue
        if got[9:12] != b"100":
            return got
        _continue, sep, rest = got.partition(b"\r\n\r\n")
        if sep:
            return rest or None


def _send_body(sock, data, size: int, deadline: float):
    """Sends size bytes of data (bytes or a binary file) a TLS record at a time, each only once the socket
    takes it, so a write never blocks; None once all is sent, or the bytes of an answer that came first (the
    agent refused before the end: were the rest written, the agent's close would reset the connection, and
    TLS would lose that answer)."""
    view = memoryview(data) if isinstance(data, (bytes, bytearray)) else None
    sent = 0
    while sent < size:
        left = deadline - time.monotonic()
        readable, writable, _x = select.select([sock], [sock], [], max(0.0, min(left, TRANSFER_TIMEOUT)))
        if readable:
            head = _recv_now(sock)
            if head is None:
                continue
            if not head:
                raise OSError(f"the agent closed the connection after {sent} of {size} bytes")
            return head
        if not writable or left <= 0:
            raise TimeoutError(f"{sent} of {size} bytes sent; the agent took no more")
        chunk = view[sent : sent + 16384] if view is not None else data.read(min(16384, size - sent))
        if not chunk:
            raise OSError(f"the file ended after {sent} of {size} bytes")
        sock.sendall(chunk)
        sent += len(chunk)
    return None


class _Replay(io.RawIOBase):
    """What was read of an answer already, then the rest from the socket: the socket http.client's
    HTTPResponse parses an early answer from."""

    def __init__(self, head: bytes, sock):
        super().__init__()
        self.head, self.sock = head, sock

    def readable(self) -> bool:
        return True

    def readinto(self, buf) -> int:
        if self.head:
            n = min(len(buf), len(self.head))
            buf[:n], self.head = self.head[:n], self.head[n:]
            return n
        return self.sock.recv_into(buf)

    def makefile(self, _mode):
        return io.BufferedReader(self)


class Limiter:
    """Per person or token: `per_minute` writes in a burst, then one every 60/per_minute s."""

    def __init__(self, per_minute: int = WRITES_PER_MINUTE, clock=time.monotonic):
        self.per_minute, self.clock = per_minute, clock
        self._lock = threading.Lock()
        self._buckets = {}

    def allow(self, key: str) -> bool:
        with self._lock:
            now = self.clock()
            level, at = self._buckets.get(key, (float(self.per_minute), now))
            level = min(float(self.per_minute), level + (now - at) * self.per_minute / 60.0)
            if level < 1.0:
                self._buckets[key] = (level, now)
                return False
            self._buckets[key] = (level - 1.0, now)
            return True


def action_body(raw: bytes) -> dict:
    """The body of an action request: empty, or a JSON object whose one field is confirm (a bool);
    (status, error) as ValueError's args otherwise."""
    if len(raw) > MAX_BODY:
        raise ValueError(413, f"the body is over {MAX_BODY} bytes")
    if not raw.strip():
        return {"confirm": False}
    try:
        body = json.loads(raw)
    except (ValueError, RecursionError) as exc:
        raise ValueError(400, f"the body is not JSON: {type(exc).__name__}") from exc
    if not isinstance(body, dict):
        raise ValueError(400, "the body is not a JSON object")
    unknown = sorted(set(body) - {"confirm"})
    if unknown:
        raise ValueError(400, f"{unknown[0]}: not a field of an action; the one field is confirm")
    if not isinstance(body.get("confirm", False), bool):
        raise ValueError(400, f"confirm: {body['confirm']!r} is not true or false")
    return {"confirm": body.get("confirm", False)}


def peer_name(cert: dict) -> str:
    """The common name of a verified peer certificate (ssl's getpeercert()). The agent's own twin
    (instance/agent.py): this script runs alone on the door, beside no copy of the agent's code."""
    for rdn in (cert or {}).get("subject", ()):
        for key, value in rdn:
            if key == "commonName":
                return value
    return ""


def another_site(headers: dict) -> bool:
    """A request another site's page sent: Sec-Fetch-Site says so, or an Origin that is not the
    door's own as nginx saw the browser reach it (X-Fleet-Origin)."""
    origin, own = headers.get("Origin"), headers.get("X-Fleet-Origin")
    return headers.get("Sec-Fetch-Site") in ("cross-site", "same-site") or (
        origin is not None and (not own or origin.rstrip("/").lower() != own.rstrip("/").lower())
    )


class Api:
    """The routes, over a Fleet and a way to ask who is calling."""

    def __init__(
        self,
        fleet: Fleet,
        identify,
        logs=None,
        log=say,
        follow=Follow,
        recheck=RECHECK_SECONDS,
        agents=None,
        limiter=None,
        pool=None,
    ):
        """identify(cookie, authorization) -> identity or None; logs(status_url, n) -> the host's text;
        follow(url, path, ctx=None) -> a Follow; agents: the Agents the actions go through."""
        self.fleet, self.identify, self.log = fleet, identify, log
        self.follow, self.recheck = follow, recheck
        self.agents = agents or Agents(fleet.config)
        self.limiter = limiter or Limiter()
        # the sessions handed out from the pool (None: no store, no sessions)
        self.pool = pool
        self.logs = logs or (lambda url, n: get(url.removesuffix("/status") + f"/logs/{n}", fleet.timeout).decode())
        self.doc = openapi()

    def answer(
        self,
        method: str,
        target: str,
        cookie: str = "",
        authorization: str = "",
        client: str = "-",
        body: bytes = b"",
        headers=None,
    ):
        """(status, content type, body bytes, or a stream: a callable of write and the client's socket).
        headers: the request's (Origin, X-Fleet-Origin, Sec-Fetch-Site, X-Fleet-CSRF) for a write."""
        url = urllib.parse.urlsplit(target)
        route, found = next(((r, m) for r, rx in _ROUTES if (m := rx.match(url.path))), (None, None))
        if route is None:
            return _json(404, {"error": f"no such path: {url.path}. See /api/docs."})
        if method not in METHODS.get(route, ("GET",)):
            allowed = ", ".join(METHODS.get(route, ("GET",)))
            return _json(405, {"error": f"{method} is not allowed on {url.path}; {allowed} is"})
        if route == "health":
            return _json(200, {"status": "ok", "version": VERSION})
        if route == "openapi":
            return _json(200, self.doc)
        if route == "docs":
            return 200, "text/html; charset=utf-8", docs_page(self.doc).encode()
        who = self.identify(cookie, authorization)
        if who is None:
            return _json(401, {"error": "log in, or send an API token (Authorization: Bearer isf_...)"})
        operator = who.get("role") == "operator"
        refused = refusal(who, route)
        if refused:
            self.log(f"refused {who_line(who)} path={url.path!r} from={client} ({refused[0]})")
            return _json(403, {"error": refused[1]})
        if route in ("sessions", "session"):
            return self.sessions(method, route, found, who, client, body, headers or {})
        if method != "GET" or route in ("actions", "action"):
            return self.act(method, route, found, who, client, body, headers or {}, url, (cookie, authorization))
        if route == "fleet":
            hosts = [self.fleet.host_view(h, operator) for h in self.fleet.hosts()]
            return _json(200, {"hosts": hosts, "user": who.get("user"), "role": who.get("role")})
        if route == "config":
            return _json(200, self.config_view(operator))
        read = next((h for h in self.fleet.hosts() if h["name"] == found["host"]), None)
        if read is None:
            return _json(404, {"error": f"no host {found['host']} behind this front door"})
        view = self.fleet.host_view(read, operator)
        if route == "host":
            return _json(200, view)
        inst = next((i for i in view["instances"] if i["id"] == int(found["n"])), None)
        if inst is None:
            return _json(404, {"error": f"no instance {found['n']} on {found['host']}"})
        if route == "instance":
            return _json(200, inst)
        query = urllib.parse.parse_qs(url.query)
        tail = query.get("tail", [str(MAX_TAIL)])[0]
        if not tail.isdigit() or not 1 <= int(tail) <= MAX_TAIL:
            return _json(400, {"error": f"tail: {tail!r} is not 1-{MAX_TAIL}"})
        backend = next(b for b in self.fleet.config["hosts"] if b["name"] == found["host"])
        if query.get("follow") == ["1"]:
            try:
                stream = self.follow(backend["status_url"], f"/logs/{int(found['n'])}?follow=1")
            except OSError as exc:
                return _json(502, {"error": f"{found['host']} did not give the journal: {exc}"})

            def still_allowed():
                again = self.identify(cookie, authorization)
                return again is not None and refusal(again, route) is None

            self.log(f"follow {who_line(who)} path={url.path!r} from={client}")
            return (
                200,
                "text/plain; charset=utf-8",
                lambda write, conn: stream.copy(write, conn, still_allowed, self.recheck),
            )
        try:
            text = self.logs(backend["status_url"], int(found["n"]))
        except (OSError, ValueError) as exc:
            return _json(502, {"error": f"{found['host']} did not give the journal: {exc}"})
        lines = text.splitlines()[-int(tail) :]
        return 200, "text/plain; charset=utf-8", ("\n".join(lines) + "\n").encode()

    def act(self, method: str, route: str, found, who: dict, client: str, raw: bytes, headers: dict, url, creds):
        """An action on an instance or a host, or what became of one: through the host's agent."""
        host = found["host"]
        if not any(b["name"] == host for b in self.fleet.config.get("hosts") or []):
            return _json(404, {"error": f"no host {host} behind this front door"})
        if not self.agents.url(host):
            return _json(
                409,
                {
                    "error": f"{host} runs no action agent the door can reach. Fix: deploy it with "
                    "isaac_sim_agent_enabled: true, then run playbooks/front_door.yml again."
                },
            )
        if route in ("actions", "action"):
            return self.read_action(route, found, url, creds)
        action = "remove" if method == "DELETE" else found["action"]
        scopes = who.get("scopes")
        held = set(scopes) if scopes is not None else set(ACTION_SCOPES.values())
        if ACTION_SCOPES[action] not in held:
            self.log(
                f"refused {who_line(who)} {action} on {host} from={client} (needs the {ACTION_SCOPES[action]} scope)"
            )
            return _json(403, {"error": f"{action} needs a token with the {ACTION_SCOPES[action]} scope"})
        if not browser_write_ok(who, headers):
            self.log(f"refused {who_line(who)} {action} on {host} from={client} (another site, or no CSRF token)")
            return _json(403, {"error": "a write from a browser needs the door's own page (Origin and X-Fleet-CSRF)"})
        try:
            body = action_body(raw)
        except ValueError as exc:
            code, error = exc.args
            return _json(code, {"error": error})
        if body["confirm"] and "operate" not in held:
            return _json(403, {"error": "confirm: going below N-1 serving instances needs the operate scope"})
        key = f"token:{who['user']}/{who['token']}" if who.get("token") else f"user:{who['user']}"
        if not self.limiter.allow(key):
            self.log(f"refused {who_line(who)} {action} on {host} from={client} (rate limit)")
            return _json(429, {"error": f"more than {self.limiter.per_minute} actions a minute; wait a little"})
        request = {"host": host, "action": action, "user": who["user"], "confirm": body["confirm"]}
        if who.get("token"):
            request["token"] = who["token"]
        if "n" in found.groupdict() and found["n"] is not None:
            request["ids"] = [int(found["n"])]
        target = f"{host}/{found['n']}" if request.get("ids") else host
        try:
            code, answer = self.agents.ask(host, "POST", "/actions", request)
        except OSError as exc:
            self.log(f"action {who_line(who)} {action} {target} from={client}: {host} did not answer ({exc})")
            return _json(
                504,
                {
                    "error": f"{host}'s agent did not answer: {exc}. The action may have been taken: see "
                    f"/api/hosts/{host}/actions before asking again."
                },
            )
        said = answer.get("id") or answer.get("error")
        self.log(f"action {who_line(who)} {action} {target} from={client}: {code} {said}")
        if code in (200, 202) and answer.get("id"):
            answer["url"] = f"/api/hosts/{host}/actions/{answer['id']}"
            answer["events"] = answer["url"] + "?follow=1"
        return _json(code, answer)

    def sessions(self, method: str, route: str, found, who: dict, client: str, raw: bytes, headers: dict):
        """A person's simulator sessions: ask (POST), look (GET), end (DELETE); an operator sees and ends all."""
        if self.pool is None:
            return _json(409, {"error": "this front door hands out no sessions (its API runs without a store)"})
        user, operator = who["user"], who.get("role") == "operator"
        scopes = set(who.get("scopes") or [])
        if method != "GET":
            if "use" not in scopes:
                self.log(f"refused {who_line(who)} {method} {route} from={client} (needs the use scope)")
                return _json(403, {"error": "sessions need a token with the use scope"})
            if not browser_write_ok(who, headers):
                self.log(f"refused {who_line(who)} {method} {route} from={client} (another site, or no CSRF token)")
                return _json(
                    403, {"error": "a write from a browser needs the door's own page (Origin and X-Fleet-CSRF)"}
                )
            key = f"token:{user}/{who['token']}" if who.get("token") else f"user:{user}"
            if not self.limiter.allow(key):
                self.log(f"refused {who_line(who)} {method} {route} from={client} (rate limit)")
                return _json(429, {"error": f"more than {self.limiter.per_minute} requests a minute; wait a little"})
        # an operator's token ends another's session only with the operate scope
        over = operator and (not who.get("token") or "operate" in scopes)
        try:
            if route == "sessions" and method == "POST":
                try:
                    body = json.loads(raw or b"{}")
                except (ValueError, RecursionError):
                    return _json(400, {"error": 'the body: not JSON. Fix: {} or {"release": "5.0"}.'})
                code, answer = self.pool.request(user, body, who.get("role") or "")
                return _json(code, answer)
            if route == "sessions":
                answer = {"user": user, "mine": self.pool.mine(user)}
                if operator:
                    answer.update(self.pool.everything())
                return _json(200, answer)
            if method == "DELETE":
                answer = self.pool.end(found["sid"], user, over)
                self.log(f"session {found['sid']} end asked by {who_line(who)} from={client}: {answer['state']}")
                return _json(200, answer)
            return _json(200, self.pool.look(found["sid"], user, operator))
        except sim_pool.RefusedError as refused:
            code, answer = refused.args
            return _json(code, answer)

    def read_action(self, route: str, found, url, creds):
        """The host's last actions, one action, or (follow=1) its events as they come."""
        host = found["host"]
        path = "/actions" if route == "actions" else f"/actions/{found['id']}"
        try:
            code, answer = self.agents.ask(host, "GET", path)
            if route == "actions" or code != 200 or urllib.parse.parse_qs(url.query).get("follow") != ["1"]:
                return _json(code, answer)
            stream = self.agents.events(host, found["id"], self.follow)
        except OSError as exc:
            return _json(504, {"error": f"{host}'s agent did not answer within {self.agents.timeout:g} s: {exc}"})

        def still_allowed():
            again = self.identify(*creds)
            return again is not None and refusal(again, route) is None

        return 200, "application/x-ndjson", lambda write, conn: stream.copy(write, conn, still_allowed, self.recheck)

    def config_view(self, operator: bool) -> dict:
        c = self.fleet.config
        out = {
            "door": c.get("door"),
            "session_hours": c.get("session_hours"),
            "relay": c.get("relay"),
            "hosts": [b["name"] for b in c.get("hosts") or []],
            "entrances": c.get("entrances") or {},
        }
        if operator:
            out["status_urls"] = {b["name"]: b["status_url"] for b in c.get("hosts") or []}
        return out


def browser_write_ok(who: dict, headers: dict) -> bool:
    """A token's write, or a person's browser on the door's own page (which read the session's CSRF
    token from /session)."""
    if who.get("token"):
        return True
    csrf = (headers.get("X-Fleet-CSRF") or "").encode("utf-8", "replace")
    return not another_site(headers) and bool(who.get("csrf")) and hmac.compare_digest(csrf, who["csrf"].encode())


def refusal(who: dict, route: str):
    """(why, for the journal; the answer's error) where who may not have the route; else None."""
    if "read" not in (who.get("scopes") or []):
        return "no read scope", "this token may not read; make one with the read scope"
    if NEEDS.get(route) == "operator" and who.get("role") != "operator":
        return f"role {who.get('role')}", "operators only"
    return None


def who_line(who: dict) -> str:
    return f"user={who.get('user')}" + (f" token={who['token']}" if who.get("token") else "")


def _json(code: int, body) -> tuple:
    return code, "application/json", (json.dumps(body, indent=1, sort_keys=True) + "\n").encode()


def handler(api: Api):
    class Handler(BaseHTTPRequestHandler):
        server_version = "isaac-sim-fleet-api"
        sys_version = ""
        timeout = 30

        def _serve(self, method: str):
            client = self.headers.get("X-Real-IP") or self.client_address[0]
            try:
                try:
                    length = int(self.headers.get("Content-Length") or 0)
                except ValueError:
                    length = MAX_BODY + 1
                if not 0 <= length <= MAX_BODY:
                    code, kind, body = _json(413, {"error": f"the body is not 0-{MAX_BODY} bytes"})
                    self.close_connection = True
                else:
                    raw = self.rfile.read(length) if length > 0 else b""
                    code, kind, body = api.answer(
                        method,
                        self.path,
                        self.headers.get("Cookie", ""),
                        self.headers.get("Authorization", ""),
                        client,
                        raw,
                        {k: self.headers.get(k) for k in _WRITE_HEADERS if self.headers.get(k) is not None},
                    )
            except Exception as error:  # pylint: disable=broad-exception-caught
                api.log(f"error path={self.path!r} from={client}: {type(error).__name__}: {error}")
                code, kind, body = _json(500, {"error": "the API failed; its journal says why"})
            self.send_response(code)
            self.send_header("Content-Type", kind)
            if callable(body):  # a stream: its end is the connection's
                self.send_header("Cache-Control", "no-store")
                # nginx passes each line on at once
                self.send_header("X-Accel-Buffering", "no")
                self.end_headers()
                self.wfile.flush()

                def write(data):
                    self.wfile.write(data)
                    self.wfile.flush()

                why = body(write, self.connection)
                api.log(f"follow ended path={self.path!r} ({why})")
                self.close_connection = True
                return
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            if kind.startswith("text/html"):
                self.send_header("Content-Security-Policy", "default-src 'none'; style-src 'unsafe-inline'")
            self.end_headers()
            self.wfile.write(body)

        def do_GET(self):  # noqa: N802 - http.server's naming
            self._serve("GET")

        def do_POST(self):  # noqa: N802
            self._serve("POST")

        def do_DELETE(self):  # noqa: N802
            self._serve("DELETE")

        def log_message(self, *args):
            pass

    return Handler


class Server(ThreadingHTTPServer):
    # a burst of requests at once (nginx passes them on as they come) waits in the kernel, never reset
    request_queue_size = 128
    daemon_threads = True


def main(argv=None):
    import argparse

    parser = argparse.ArgumentParser(description="The fleet's API on the front door (isaacsim.fleet)")
    parser.add_argument("--port", type=int)
    parser.add_argument("--config", required=True, help="the door's api.json (the role writes it)")
    parser.add_argument("--auth", help="the login service's URL (http://127.0.0.1:PORT)")
    parser.add_argument("--ttl", type=float, default=2.0, help="seconds a host's status read is reused")
    parser.add_argument("--agent-tls", default="", help="a directory of ca.crt, client.crt, client.key")
    parser.add_argument("--store", default="", help="the login service's SQLite file: sessions are kept there")
    parser.add_argument("--metrics-dir", default="", help="node_exporter's textfile directory (the sessions' figures)")
    parser.add_argument(
        "--end-sessions",
        metavar="WHY",
        default="",
        help="serve nothing: end every session and place (the door's removal), print what was done as JSON",
    )
    parser.add_argument("--wait", type=float, default=120.0, help="seconds --end-sessions waits for the hosts")
    args = parser.parse_args(argv)
    if args.end_sessions and not args.store:
        parser.error("--end-sessions needs --store")
    if not args.end_sessions and (args.port is None or not args.auth):
        parser.error("--port and --auth are needed to serve")
    with open(args.config, encoding="utf-8") as f:
        config = json.load(f)
    fleet = Fleet(config, ttl=args.ttl)
    tls = None
    # (a door whose hosts run no agent has none: its removal has no claim to give back)
    if args.agent_tls and (not args.end_sessions or os.path.isdir(args.agent_tls)):
        tls = {
            k: f"{args.agent_tls}/{name}"
            for k, name in (("ca", "ca.crt"), ("cert", "client.crt"), ("key", "client.key"))
        }
    agents = Agents(config, tls)
    pool = None
    if args.end_sessions:
        # run by the role, not as the service: its lines go to the journal under the service's name, the
        # answer alone to stdout
        import syslog  # pylint: disable=import-outside-toplevel

        syslog.openlog("isaac-sim-front-door-api")
        ending = sim_pool.Pool(sim_pool.Store(args.store), fleet, agents, config.get("pool"), log=syslog.syslog)
        sys.stdout.write(json.dumps(ending.end_all(args.end_sessions, args.wait)) + "\n")
        sys.stdout.flush()
        return
    if args.store:
        pool = sim_pool.Pool(sim_pool.Store(args.store), fleet, agents, config.get("pool"), log=say)
        threading.Thread(
            target=pool.run, args=(threading.Event(),), kwargs={"metrics_dir": args.metrics_dir}, daemon=True
        ).start()
    api = Api(
        fleet,
        lambda cookie, authorization: ask_identity(args.auth, cookie, authorization),
        agents=agents,
        pool=pool,
    )
    Server(("127.0.0.1", args.port), handler(api)).serve_forever()


if __name__ == "__main__":
    main()
