"""The Docker Engine API client (module_utils/hostlib/docker_socket.py) against a socket that answers like dockerd."""

from __future__ import annotations

import http.server
import json
import socketserver
import threading
from urllib.parse import parse_qs, urlparse

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerError, DockerSocket
from ansible_collections.isaacsim.fleet.tests.unit.helpers import recorded


class _Server(socketserver.ThreadingMixIn, socketserver.UnixStreamServer):
    daemon_threads = True


DISTRIBUTION = {
    "Descriptor": {
        "mediaType": "application/vnd.docker.distribution.manifest.v2+json",
        "digest": "sha256:" + "ab" * 32,
        "size": 1570,
    },
    "Platforms": [{"architecture": "amd64", "os": "linux"}],
}


class _Dockerd(http.server.BaseHTTPRequestHandler):
    asked = []
    auth = []

    def address_string(self):  # a unix socket has no client address
        return "unix"

    def do_GET(self):  # noqa: N802 - http.server's naming
        self.asked.append(self.path)
        url = urlparse(self.path)
        if url.path == "/v1.41/containers/json":
            status, body = 200, recorded("docker-containers.json")
        elif url.path == "/v1.41/images/json":
            status, body = 200, recorded("docker-images.json")
        elif url.path.startswith("/v1.41/distribution/"):
            self.auth.append(self.headers.get("X-Registry-Auth"))
            status, body = 200, json.dumps(DISTRIBUTION)
        else:
            status, body = 404, '{"message": "page not found"}'
        data = body.encode()
        self.send_response(status)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(data)))
        self.end_headers()
        self.wfile.write(data)

    def log_message(self, *args):
        pass


@pytest.fixture()
def dockerd(tmp_path):
    path = str(tmp_path / "docker.sock")
    _Dockerd.asked = []
    _Dockerd.auth = []
    server = _Server(path, _Dockerd)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield path
    server.shutdown()
    server.server_close()


def test_containers_are_listed_in_one_call_with_a_name_filter(dockerd):
    docker = DockerSocket(f"unix://{dockerd}")
    names = [c["Names"][0] for c in docker.containers("isaac-sim-")]
    assert "/isaac-sim-0" in names
    assert docker.calls == 1
    query = parse_qs(urlparse(_Dockerd.asked[0]).query)
    assert query["all"] == ["1"] and json.loads(query["filters"][0]) == {"name": ["isaac-sim-"]}


def test_images_and_the_call_count(dockerd):
    docker = DockerSocket(dockerd)
    assert docker.images() and docker.calls == 1


def test_an_error_answer_names_the_status(dockerd):
    with pytest.raises(DockerError, match="Docker answered 404 to GET /nothing"):
        DockerSocket(dockerd).get("/nothing")


def test_no_daemon_says_where_it_looked(tmp_path):
    docker = DockerSocket(str(tmp_path / "absent.sock"))
    with pytest.raises(DockerError, match="cannot reach the Docker daemon at .*absent.sock"):
        docker.containers("isaac-sim-")
    assert docker.calls == 1


class _ChunkedDockerd(_Dockerd):
    """Answers as Go's net/http does for a large body: HTTP/1.1, chunked, closing after it."""

    protocol_version = "HTTP/1.1"

    def do_GET(self):  # noqa: N802 - http.server's naming
        data = recorded("docker-containers.json").encode()
        self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.send_header("Transfer-Encoding", "chunked")
        self.send_header("Connection", "close")
        self.end_headers()
        for at in range(0, len(data), 1000):
            piece = data[at : at + 1000]
            self.wfile.write(f"{len(piece):x};ext=1\r\n".encode() + piece + b"\r\n")
        self.wfile.write(b"0\r\nX-Trailer: t\r\n\r\n")
        self.close_connection = True


def test_a_chunked_answer_reads_whole(tmp_path):
    path = str(tmp_path / "docker.sock")
    server = _Server(path, _ChunkedDockerd)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        got = DockerSocket(path).containers("isaac-sim-")
    finally:
        server.shutdown()
        server.server_close()
    assert got == json.loads(recorded("docker-containers.json"))


def test_an_answer_that_is_not_http_is_a_docker_error(tmp_path):
    import socket

    path = str(tmp_path / "docker.sock")
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    listener.bind(path)
    listener.listen(1)

    def answer():
        conn, _addr = listener.accept()
        conn.recv(4096)
        conn.sendall(b"garbage")
        conn.close()

    thread = threading.Thread(target=answer, daemon=True)
    thread.start()
    try:
        with pytest.raises(DockerError, match="answered GET /images/json unreadably: not an HTTP response"):
            DockerSocket(path).images()
    finally:
        listener.close()
        thread.join(5)


def test_the_registry_is_asked_through_the_daemon_with_the_credentials_in_a_header(dockerd):
    docker = DockerSocket(f"unix://{dockerd}")
    assert docker.distribution("reg.lab:5000/isaac-sim:6.0.1", "eyJ1c2VybmFtZSI6") == DISTRIBUTION
    assert docker.distribution("reg.lab:5000/isaac-sim:6.0.1") == DISTRIBUTION
    # the reference as the docker CLI sends it; the header only when there are credentials
    assert _Dockerd.asked == ["/v1.41/distribution/reg.lab:5000/isaac-sim:6.0.1/json"] * 2
    assert _Dockerd.auth == ["eyJ1c2VybmFtZSI6", None]
