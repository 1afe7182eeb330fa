# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""A host's read-only status endpoint (isaac-sim-status.service): what isaac_sim_info
returns, as the fleet dashboard shows it, served as JSON to the networks allowed.

GET only, no control: changes go through Ansible. Answers are computed at most
once per `ttl` seconds however many dashboards ask, so a page left open on many desks
costs the host one status read per period. An instance's recent journal, at /logs/N, only to
the networks of isaac_sim_status_server_logs_allow (none by default: the front door's address,
which passes it on to operators alone); /logs/N?follow=1 keeps sending its new lines (journalctl
-f), at most FOLLOWERS at once, each for FOLLOW_SECONDS at most, and ends as soon as the client
goes.
"""

from __future__ import annotations

import contextlib
import http.server
import ipaddress
import json
import os
import re
import select
import socket
import subprocess
import threading
import time
import urllib.parse

PATH = "/status"
LOGS_RE = re.compile(r"^/logs/([0-9]{1,2})\Z")
LOG_LINES = 200
# journal streams at once, and how long each may run (a page left open ends; it asks again)
FOLLOWERS = 8
FOLLOW_SECONDS = 3600
# the address families the dashboard may come from; a private fleet by default
DEFAULT_ALLOW = ("127.0.0.0/8", "10.0.0.0/8", "172.16.0.0/12", "192.168.0.0/16", "::1/128", "fc00::/7")


def parse_networks(texts, name="isaac_sim_status_server_allow") -> tuple[list, list]:
    """(networks, errors) for the allowed networks as written (CIDR or single addresses)."""
    networks, errors = [], []
    for text in texts or []:
        try:
            networks.append(ipaddress.ip_network(str(text).strip(), strict=False))
        except ValueError:
            errors.append(
                f"{name}: {text!r} is not a network. Fix: write it as CIDR, e.g. 10.20.0.0/16, or a single address."
            )
    return networks, errors


def journal_argv(unit: str, lines: int = LOG_LINES, follow: bool = False) -> list:
    """journalctl's argv for a unit's last lines, as plain text with ISO time stamps (follow: then
    each new line as it comes)."""
    argv = ["journalctl", "-u", unit, "-n", str(int(lines)), "-o", "short-iso", "--no-pager", "-q"]
    return argv + (["-f"] if follow else [])


def stream(proc, connection, write, seconds: float = FOLLOW_SECONDS, clock=time.monotonic) -> str:
    """Copies proc's output to write() until the client goes (its socket reads as closed), the
    output ends, or seconds pass; the process is ended either way. Why it ended."""
    deadline = clock() + seconds
    why, budget = "time", 65536
    try:
        while clock() < deadline:
            ready, _w, _x = select.select([proc.stdout, connection], [], [], 1.0)
            if connection in ready:
                # what the client sends now is read and dropped (select would wake for it again);
                # closed, or past 64 KiB, it is gone
                try:
                    data = connection.recv(65536)
                except OSError:
                    data = b""
                budget -= len(data)
                if not data or budget < 0:
                    why = "client gone"
                    break
            if proc.stdout in ready:
                # the pipe itself, unbuffered: a buffered readline would keep lines select() cannot see
                chunk = os.read(proc.stdout.fileno(), 65536)
                if not chunk:
                    why = "output ended"
                    break
                try:
                    write(chunk)
                except OSError:
                    why = "client gone"
                    break
    finally:
        proc.kill()
        proc.wait()
    return why


def allowed(address: str, networks) -> bool:
    try:
        ip = ipaddress.ip_address(address.split("%", 1)[0])
    except ValueError:
        return False
    # an IPv4 client on an IPv6 socket arrives as ::ffff:a.b.c.d
    if ip.version == 6 and ip.ipv4_mapped:
        ip = ip.ipv4_mapped
    return any(ip in net for net in networks if net.version == ip.version)


class Cache:
    """One status read per ttl seconds; concurrent requests wait for the same read."""

    def __init__(self, read, ttl: float, clock=time.monotonic):
        self._read, self._ttl, self._clock = read, ttl, clock
        self._lock = threading.Lock()
        self._at, self._body = None, b""
        self.reads = 0

    def get(self) -> bytes:
        with self._lock:
            now = self._clock()
            if self._at is None or now - self._at >= self._ttl:
                self._body = json.dumps(self._read(), sort_keys=True).encode()
                self._at = now
                self.reads += 1
            return self._body


FORBIDDEN = (
    b"HTTP/1.0 403 Forbidden\r\nContent-Type: text/plain\r\nConnection: close\r\n\r\n"
    b"forbidden: this address is not in isaac_sim_status_server_allow\n"
)


def cors_origin(origin, origins):
    """The Access-Control-Allow-Origin to send: the page's origin when it is one allowed, else none.
    "null" is a dashboard opened as a file (and any sandboxed frame: see docs/docsite/rst/operate.rst)."""
    return origin if origin is not None and origin in origins else None


def handler(cache: Cache, networks, origins=("null",), logs=None, logs_networks=(), follow=None):
    """logs: instance number -> its journal's last lines (bytes); follow: instance number -> a
    process whose stdout is its journal as it grows; both served to logs_networks alone."""
    followers = threading.BoundedSemaphore(FOLLOWERS)

    class Handler(http.server.BaseHTTPRequestHandler):
        server_version = "isaac-sim-status"
        sys_version = ""
        # a client that connects and sends nothing does not keep a thread for long
        timeout = 10

        def _send(self, code, body: bytes, content_type="text/plain; charset=utf-8", extra=()):
            self.send_response(code)
            self.send_header("Content-Type", content_type)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.send_header("X-Content-Type-Options", "nosniff")
            # which pages may read it in a browser: the dashboard's origin only
            allow_origin = cors_origin(self.headers.get("Origin"), origins)
            if allow_origin:
                self.send_header("Access-Control-Allow-Origin", allow_origin)
                self.send_header("Vary", "Origin")
            for name, value in extra:
                self.send_header(name, value)
            self.end_headers()
            if self.command != "HEAD":
                self.wfile.write(body)

        def _allowed(self) -> bool:
            if allowed(self.client_address[0], networks):
                return True
            self._send(403, b"forbidden: this address is not in isaac_sim_status_server_allow\n")
            return False

        def do_GET(self):  # noqa: N802 - http.server's naming
            if not self._allowed():
                return
            path = self.path.split("?", 1)[0]
            wanted = LOGS_RE.fullmatch(path)
            if wanted:
                query = urllib.parse.parse_qs(urllib.parse.urlsplit(self.path).query)
                if query.get("follow") == ["1"]:
                    self._follow(int(wanted.group(1)))
                else:
                    self._logs(int(wanted.group(1)))
                return
            if path not in (PATH, PATH + "/"):
                self._send(404, f"not found: the status is at {PATH}\n".encode())
                return
            try:
                body = cache.get()
            except Exception as exc:  # the host's status could not be read: say so, keep serving
                self._send(503, f"status unavailable: {exc}\n".encode())
                return
            self._send(200, body, "application/json")

        def _logs(self, instance: int):
            if logs is None or not allowed(self.client_address[0], logs_networks):
                self._send(403, b"forbidden: logs go to isaac_sim_status_server_logs_allow alone\n")
                return
            try:
                body = logs(instance)
            except Exception as exc:  # the journal could not be read: say so, keep serving
                self._send(503, f"logs unavailable: {exc}\n".encode())
                return
            self._send(200, body)

        def _follow(self, instance: int):
            if follow is None or not allowed(self.client_address[0], logs_networks):
                self._send(403, b"forbidden: logs go to isaac_sim_status_server_logs_allow alone\n")
                return
            if not followers.acquire(blocking=False):
                self._send(503, f"busy: {FOLLOWERS} journals are followed already; try again later\n".encode())
                return
            try:
                proc = follow(instance)
                self.send_response(200)
                self.send_header("Content-Type", "text/plain; charset=utf-8")
                self.send_header("Cache-Control", "no-store")
                self.send_header("X-Content-Type-Options", "nosniff")
                self.end_headers()
                self.wfile.flush()

                def write(chunk):
                    self.wfile.write(chunk)
                    self.wfile.flush()

                # the request's end is known (no body): anything the client sends now means it went
                stream(proc, self.connection, write)
                self.close_connection = True
            finally:
                followers.release()

        do_HEAD = do_GET  # noqa: N815

        def _refuse(self):
            if self._allowed():
                self._send(405, b"read-only: GET only\n", extra=(("Allow", "GET, HEAD"),))

        do_POST = do_PUT = do_DELETE = do_PATCH = _refuse  # noqa: N815

        def log_message(self, *args):
            pass

    return Handler


class _Server(http.server.ThreadingHTTPServer):
    networks: list = []

    def verify_request(self, request, client_address):
        # a client outside the allowed networks is answered 403 and dropped before a byte of its
        # request is read: it never holds a thread
        if allowed(client_address[0], self.networks):
            return True
        with contextlib.suppress(OSError):
            request.sendall(FORBIDDEN)
        return False


def follow_process(unit: str):
    """journalctl following a unit's journal, its lines on stdout."""
    return subprocess.Popen(journal_argv(unit, 20, follow=True), stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)


def server(
    address: str, port: int, cache: Cache, networks, origins=("null",), logs=None, logs_networks=(), follow=None
) -> http.server.ThreadingHTTPServer:
    srv_class = _Server
    if ":" in address:
        srv_class = type("V6", (_Server,), {"address_family": socket.AF_INET6})
    srv = srv_class((address, port), handler(cache, networks, tuple(origins), logs, tuple(logs_networks), follow))
    srv.networks = networks
    srv.daemon_threads = True
    return srv
