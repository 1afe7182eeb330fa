# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The smallest Docker Engine API client the status code needs.

Speaks HTTP/1.1 over the daemon's unix socket with a plain socket, so the
status module and the metrics timer need neither the docker CLI (a process
per call) nor the Docker SDK on the host. Not http.client: importing it (and
the email and ssl packages it pulls in) cost the status module more than its
whole read of Docker. Every request is counted: the status module promises a
fixed number of API calls per host.
"""

from __future__ import annotations

import json
import socket
from urllib.parse import quote

DEFAULT_SOCKET = "/var/run/docker.sock"
# Docker 20.10 (Debian 12's docker.io) speaks 1.41; later engines accept it too.
API_VERSION = "1.41"


class DockerError(Exception):
    def __init__(self, message, status=None):
        super().__init__(message)
        self.status = status


def _exchange(path: str, target: str, timeout, headers=None) -> bytes:
    """The daemon's whole answer to one GET; it closes the connection after it (Connection: close)."""
    extra = "".join(f"{name}: {value}\r\n" for name, value in (headers or {}).items())
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as sock:
        sock.settimeout(timeout)
        sock.connect(path)
        sock.sendall(f"GET {target} HTTP/1.1\r\nHost: docker\r\n{extra}Connection: close\r\n\r\n".encode("ascii"))
        parts = []
        while True:
            data = sock.recv(65536)
            if not data:
                return b"".join(parts)
            parts.append(data)


def _dechunk(body: bytes) -> bytes:
    """A chunked body (Transfer-Encoding: chunked) made whole; trailers are dropped."""
    out, at = [], 0
    while True:
        eol = body.index(b"\r\n", at)
        size = int(body[at:eol].split(b";", 1)[0], 16)
        if size == 0:
            return b"".join(out)
        out.append(body[eol + 2 : eol + 2 + size])
        at = eol + 2 + size + 2


def parse_response(raw: bytes) -> tuple:
    """(status, body) of an HTTP/1.x response as the daemon sends it."""
    head, sep, body = raw.partition(b"\r\n\r\n")
    lines = head.decode("iso-8859-1").split("\r\n")
    fields = lines[0].split(" ", 2)
    if not sep or len(fields) < 2 or not fields[0].startswith("HTTP/") or not fields[1].isdigit():
        raise ValueError(f"not an HTTP response: {raw[:80]!r}")
    headers = {}
    for line in lines[1:]:
        name, _colon, value = line.partition(":")
        headers[name.strip().lower()] = value.strip()
    if "chunked" in headers.get("transfer-encoding", "").lower():
        body = _dechunk(body)
    elif headers.get("content-length", "").isdigit():
        body = body[: int(headers["content-length"])]
    return int(fields[1]), body


class DockerSocket:
    def __init__(self, path=DEFAULT_SOCKET, timeout=10):
        self.path = path[len("unix://") :] if path.startswith("unix://") else path
        self.timeout = timeout
        self.calls = 0

    def get(self, endpoint: str, headers=None):
        """The decoded JSON answer of GET /v1.41{endpoint}."""
        self.calls += 1
        try:
            status, body = parse_response(_exchange(self.path, f"/v{API_VERSION}{endpoint}", self.timeout, headers))
        except OSError as exc:
            raise DockerError(f"cannot reach the Docker daemon at {self.path}: {exc}") from exc
        except ValueError as exc:  # a cut or garbled answer
            raise DockerError(f"the Docker daemon at {self.path} answered GET {endpoint} unreadably: {exc}") from exc
        if status != 200:
            raise DockerError(f"Docker answered {status} to GET {endpoint}: {body[:200]!r}", status)
        return json.loads(body)

    def containers(self, name_prefix: str):
        """Every container (running or not) whose name contains name_prefix: one call."""
        filters = quote(json.dumps({"name": [name_prefix]}))
        return self.get(f"/containers/json?all=1&filters={filters}")

    def labelled(self, label: str):
        """Every container (running or not) carrying label (KEY or KEY=VALUE): one call."""
        filters = quote(json.dumps({"label": [label]}))
        return self.get(f"/containers/json?all=1&filters={filters}")

    def stats(self, container: str):
        """One sample of a container's CPU and memory use (one-shot: no wait for a second sample)."""
        return self.get(f"/containers/{quote(container)}/stats?stream=false&one-shot=true")

    def found(self, endpoint: str):
        """The answer of GET endpoint, or None when Docker has no such object (404)."""
        try:
            return self.get(endpoint)
        except DockerError as exc:
            if exc.status == 404:
                return None
            raise

    def image(self, name: str):
        """The image `name` as docker image inspect describes it, or None: one call."""
        return self.found(f"/images/{quote(name)}/json")

    def images(self):
        """Every image with its repo digests: one call."""
        return self.get("/images/json")

    def distribution(self, name: str, auth: str = ""):
        """What the image's registry says of `name` (its manifest's digest), asked by the daemon with
        its own registry settings; auth: an X-Registry-Auth value (the credentials travel over the
        socket for this one call, and are written nowhere)."""
        return self.get(f"/distribution/{quote(name, safe='/:@')}/json", {"X-Registry-Auth": auth} if auth else None)

    def network(self, name: str):
        """The network `name` as Docker describes it (docker network inspect's object), or None: one call."""
        return self.found(f"/networks/{quote(name)}")
