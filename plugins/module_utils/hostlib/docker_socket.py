# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The smallest Docker Engine API client the status code needs.

Speaks HTTP over the daemon's unix socket with the standard library, so the
status module and the metrics timer need neither the docker CLI (a process
per call) nor the Docker SDK on the host. Every request is counted: the
status module promises a fixed number of API calls per host.
"""

from __future__ import annotations

import http.client
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


class _UnixConnection(http.client.HTTPConnection):
    def __init__(self, path, timeout):
        super().__init__("localhost", timeout=timeout)
        self._path = path

    def connect(self):
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        sock.settimeout(self.timeout)
        sock.connect(self._path)
        self.sock = sock


class DockerSocket:
    def __init__(self, path=DEFAULT_SOCKET, timeout=10):
        self.path = path[len("unix://") :] if path.startswith("unix://") else path
        self.timeout = timeout
        self.calls = 0

    def get(self, endpoint: str):
        """The decoded JSON answer of GET /v1.41{endpoint}."""
        self.calls += 1
        conn = _UnixConnection(self.path, self.timeout)
        try:
            conn.request("GET", f"/v{API_VERSION}{endpoint}")
            resp = conn.getresponse()
            body = resp.read()
        except OSError as exc:
            raise DockerError(f"cannot reach the Docker daemon at {self.path}: {exc}") from exc
        finally:
            conn.close()
        if resp.status != 200:
            raise DockerError(f"Docker answered {resp.status} to GET {endpoint}: {body[:200]!r}", resp.status)
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

    def network(self, name: str):
        """The network `name` as Docker describes it (docker network inspect's object), or None: one call."""
        return self.found(f"/networks/{quote(name)}")
