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

import html
import http.client
import json
import re
import select
import socket
import sys
import threading
import time
import urllib.parse
from concurrent.futures import ThreadPoolExecutor
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

VERSION = "1"
MAX_TAIL = 200
# a host's answer: read whole within the timeout, at most this big
MAX_ANSWER = 16 * 1024 * 1024
# a followed journal asks again who is reading this often: a logout or a revoked token ends it
RECHECK_SECONDS = 10
_HOST = r"(?P<host>[A-Za-z0-9._-]+)"
_ROUTES = [
    ("health", re.compile(r"^/api/health$")),
    ("openapi", re.compile(r"^/api/openapi\.json$")),
    ("docs", re.compile(r"^/api/docs$")),
    ("fleet", re.compile(r"^/api/fleet$")),
    ("config", re.compile(r"^/api/config$")),
    ("host", re.compile(rf"^/api/hosts/{_HOST}$")),
    ("instance", re.compile(rf"^/api/hosts/{_HOST}/instances/(?P<n>[0-9]{{1,2}})$")),
    ("logs", re.compile(rf"^/api/hosts/{_HOST}/instances/(?P<n>[0-9]{{1,2}})/logs$")),
]
# what each route needs: nothing (health, the API's own description), a session or token that may
# read, or an operator's
NEEDS = {"health": None, "openapi": None, "docs": None, "logs": "operator"}


def instance_view(host: str, inst: dict, entrance, operator: bool) -> dict:
    """An instance as the API gives it: what a person needs to pick one and what holds it. Direct
    addresses (urls) go to operators alone, as on the dashboard."""
    container = inst.get("container") or {}
    run = container.get("test_run")
    view = {
        "host": host,
        "id": inst.get("id"),
        "name": inst.get("name"),
        "state": inst.get("state"),
        "ready": bool(inst.get("ready")),
        "release": inst.get("release"),
        "profile": inst.get("profile"),
        "image": inst.get("image"),
        "digest": inst.get("digest"),
        "ports": inst.get("ports") or {},
        "entrance": entrance,
        # a test run lends an instance (experience.yml, test_suite.yml); sessions come later
        "holder": {"kind": "test_run", "id": run} if run else None,
        "health": inst.get("health"),
        "restarts": inst.get("restarts"),
        "uptime_s": inst.get("uptime_s"),
        "down_reason": inst.get("down_reason"),
    }
    if operator:
        view["urls"] = inst.get("urls") or {}
    return view


class Fleet:
    """The hosts behind the door and their last status read, refreshed at most once per ttl."""

    def __init__(self, config: dict, ttl: float = 2.0, timeout: float = 5.0, fetch=None, clock=time.monotonic):
        self.config, self.ttl, self.timeout, self.clock = config, ttl, timeout, clock
        self.fetch = fetch or self._fetch
        self._lock = threading.Lock()
        self._at, self._hosts = None, []

    def _fetch(self, url: str) -> bytes:
        return get(url, self.timeout)

    def _read(self, backend: dict) -> dict:
        try:
            status = json.loads(self.fetch(backend["status_url"]))
            if not isinstance(status, dict):
                raise ValueError("the answer is not a JSON object")
            return {"name": backend["name"], "reachable": True, "error": status.get("error"), "status": status}
        # whatever one host answers (or not), the others are still served
        except Exception as exc:  # pylint: disable=broad-exception-caught
            return {"name": backend["name"], "reachable": False, "error": f"{type(exc).__name__}: {exc}", "status": {}}

    def hosts(self) -> list:
        with self._lock:
            now = self.clock()
            if self._at is None or now - self._at >= self.ttl:
                backends = self.config.get("hosts") or []
                with ThreadPoolExecutor(max_workers=max(1, min(16, len(backends)))) as pool:
                    self._hosts = list(pool.map(self._read, backends))
                self._at = now
            return self._hosts

    def host_view(self, read: dict, operator: bool) -> dict:
        status = read["status"]
        entrances = (self.config.get("entrances") or {}).get(read["name"]) or {}
        return {
            "name": read["name"],
            "reachable": read["reachable"],
            "error": read["error"],
            "generated_at": status.get("generated_at"),
            "deployed": status.get("deployed"),
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
        out = {"summary": summary, "responses": answers, "parameters": list(params)}
        if need is None:
            out["security"] = []
        return dict(out, **(extra or {}))

    host = {"name": "host", "in": "path", "required": True, "schema": {"type": "string"}}
    n = {"name": "n", "in": "path", "required": True, "schema": {"type": "integer", "minimum": 0, "maximum": 99}}
    tail = {"name": "tail", "in": "query", "schema": {"type": "integer", "minimum": 1, "maximum": MAX_TAIL}}
    follow = {
        "name": "follow",
        "in": "query",
        "description": "1: then each new line as it comes, while the session or token lasts",
        "schema": {"type": "integer", "enum": [1]},
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
            "/api/hosts/{host}/instances/{n}": {"get": op("One instance", [host, n])},
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
    """A host's followed journal (its status endpoint's /logs/N?follow=1), open and answering 200,
    to be copied to a client while the one who asked may still read it."""

    def __init__(self, status_url: str, n: int, timeout: float = 10.0):
        address = urllib.parse.urlsplit(status_url)
        self.sock = socket.create_connection((address.hostname, address.port), timeout=timeout)
        self.sock.sendall(f"GET /logs/{n}?follow=1 HTTP/1.0\r\nHost: {address.netloc}\r\n\r\n".encode())
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

    def copy(self, write, client, still_allowed, recheck: float = RECHECK_SECONDS, clock=time.monotonic) -> str:
        """Copies until the host's stream ends, the client goes, or still_allowed() says no (asked
        every recheck seconds); why it ended."""
        why, asked, budget = "host ended", clock(), [65536]
        try:
            if self.rest:
                write(self.rest)
            while True:
                ready, _w, _x = select.select([self.sock, client], [], [], 1.0)
                if client in ready and not drain(client, budget):
                    return "client gone"
                if self.sock in ready:
                    data = self.sock.recv(65536)
                    if not data:
                        return why
                    write(data)
                if clock() - asked >= recheck:
                    asked = clock()
                    if not still_allowed():
                        write(b"\n[the session or token ended: the journal stops here]\n")
                        return "access ended"
        except OSError:
            return "client gone"
        finally:
            self.sock.close()


class Api:
    """The routes, over a Fleet and a way to ask who is calling."""

    def __init__(self, fleet: Fleet, identify, logs=None, log=say, follow=Follow, recheck=RECHECK_SECONDS):
        """identify(cookie, authorization) -> identity or None; logs(status_url, n) -> the host's text;
        follow(status_url, n) -> a Follow."""
        self.fleet, self.identify, self.log = fleet, identify, log
        self.follow, self.recheck = follow, recheck
        self.logs = logs or (lambda url, n: get(url.removesuffix("/status") + f"/logs/{n}", fleet.timeout).decode())
        self.doc = openapi()

    def answer(self, method: str, target: str, cookie: str = "", authorization: str = "", client: str = "-"):
        """(status, content type, body bytes)."""
        url = urllib.parse.urlsplit(target)
        route, found = next(((r, m) for r, rx in _ROUTES if (m := rx.match(url.path))), (None, None))
        if route is None:
            return _json(404, {"error": f"no such path: {url.path}. See /api/docs."})
        if method != "GET":
            return _json(405, {"error": f"{method} is not allowed here; this API only reads for now."})
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
                stream = self.follow(backend["status_url"], int(found["n"]))
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
                code, kind, body = api.answer(
                    method, self.path, self.headers.get("Cookie", ""), self.headers.get("Authorization", ""), client
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


def main(argv=None):
    import argparse

    parser = argparse.ArgumentParser(description="The fleet's API on the front door (isaacsim.fleet)")
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--config", required=True, help="the door's api.json (the role writes it)")
    parser.add_argument("--auth", required=True, help="the login service's URL (http://127.0.0.1:PORT)")
    parser.add_argument("--ttl", type=float, default=2.0, help="seconds a host's status read is reused")
    args = parser.parse_args(argv)
    with open(args.config, encoding="utf-8") as f:
        config = json.load(f)
    fleet = Fleet(config, ttl=args.ttl)
    api = Api(fleet, lambda cookie, authorization: ask_identity(args.auth, cookie, authorization))
    ThreadingHTTPServer(("127.0.0.1", args.port), handler(api)).serve_forever()


if __name__ == "__main__":
    main()
