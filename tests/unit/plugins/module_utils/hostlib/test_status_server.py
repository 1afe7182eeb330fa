"""The host's read-only status endpoint (module_utils/hostlib/status_server.py), served for real on 127.0.0.1."""

from __future__ import annotations

import contextlib
import json
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import status_server


@contextlib.contextmanager
def serving(read, allow=("127.0.0.0/8",), ttl=60.0, logs=None, logs_allow=(), follow=None):
    networks, errors = status_server.parse_networks(allow)
    logs_networks, logs_errors = status_server.parse_networks(logs_allow)
    assert errors == logs_errors == []
    cache = status_server.Cache(read, ttl)
    srv = status_server.server("127.0.0.1", 0, cache, networks, logs=logs, logs_networks=logs_networks, follow=follow)
    threading.Thread(target=srv.serve_forever, daemon=True).start()
    try:
        yield f"http://127.0.0.1:{srv.server_address[1]}", cache
    finally:
        srv.shutdown()
        srv.server_close()


def call(url, method="GET", origin=None):
    request = urllib.request.Request(url, method=method, headers={"Origin": origin} if origin else {})
    try:
        with urllib.request.urlopen(request, timeout=5) as response:
            return response.status, dict(response.headers), response.read()
    except urllib.error.HTTPError as exc:
        return exc.code, dict(exc.headers), exc.read()


def test_status_is_json_readable_by_the_dashboard_only_and_read_once_per_period():
    with serving(lambda: {"host": "gpu-1", "instances": [{"id": 0, "state": "ready"}]}) as (url, cache):
        code, headers, body = call(url + "/status")
        assert code == 200 and headers["Content-Type"] == "application/json"
        assert json.loads(body) == {"host": "gpu-1", "instances": [{"id": 0, "state": "ready"}]}
        assert headers["Cache-Control"] == "no-store" and "Access-Control-Allow-Origin" not in headers
        # a browser lets a page read it only when the answer names the page's origin: the dashboard
        # opened as a file ("null"), not a web site the operator happens to visit
        assert call(url + "/status", origin="null")[1]["Access-Control-Allow-Origin"] == "null"
        assert "Access-Control-Allow-Origin" not in call(url + "/status", origin="https://evil.example")[1]
        for _n in range(5):
            assert call(url + "/status")[0] == 200
        assert cache.reads == 1


def test_the_period_bounds_the_reads():
    now = [0.0]
    reads = iter(range(100))
    cache = status_server.Cache(lambda: {"n": next(reads)}, ttl=2, clock=lambda: now[0])
    assert json.loads(cache.get()) == {"n": 0}
    now[0] = 1.9
    assert json.loads(cache.get()) == {"n": 0}
    now[0] = 2.0
    assert json.loads(cache.get()) == {"n": 1}


def test_read_only_one_path_and_only_the_networks_allowed():
    with serving(lambda: {}) as (url, _cache):
        assert call(url + "/")[0] == 404
        code, headers, _body = call(url + "/status", method="POST")
        assert code == 405 and headers["Allow"] == "GET, HEAD"
        assert call(url + "/status", method="DELETE")[0] == 405
    with serving(lambda: {"secret": "no"}, allow=("10.20.0.0/16",)) as (url, cache):
        code, _headers, body = call(url + "/status")
        assert code == 403 and b"isaac_sim_status_server_allow" in body
        assert cache.reads == 0


def test_a_refused_or_silent_client_holds_no_thread():
    with serving(lambda: {}, allow=("10.20.0.0/16",)) as (url, _cache):
        port = int(url.rsplit(":", 1)[1])
        before = threading.active_count()
        idle = [socket.create_connection(("127.0.0.1", port)) for _n in range(5)]
        try:
            # answered and closed at once, without reading a request
            assert idle[0].recv(64).startswith(b"HTTP/1.0 403")
            time.sleep(0.2)
            assert threading.active_count() == before
        finally:
            for conn in idle:
                conn.close()


def test_a_failed_read_is_503_and_the_server_keeps_serving():
    answers = iter([RuntimeError("docker.sock: permission denied"), {"ok": True}])

    def read():
        answer = next(answers)
        if isinstance(answer, Exception):
            raise answer
        return answer

    with serving(read, ttl=0) as (url, _cache):
        code, _headers, body = call(url + "/status")
        assert code == 503 and b"permission denied" in body
        assert call(url + "/status")[:1] == (200,)


@pytest.mark.parametrize(
    "address, allow, expected",
    [
        ("10.1.2.3", ["10.0.0.0/8"], True),
        ("192.0.2.7", ["10.0.0.0/8"], False),
        ("::ffff:10.1.2.3", ["10.0.0.0/8"], True),
        ("fd00::5", list(status_server.DEFAULT_ALLOW), True),
        ("203.0.113.9", list(status_server.DEFAULT_ALLOW), False),
        ("not-an-ip", ["0.0.0.0/0"], False),
    ],
)
def test_allowed(address, allow, expected):
    networks, _errors = status_server.parse_networks(allow)
    assert status_server.allowed(address, networks) is expected


def test_a_network_that_does_not_parse_is_named():
    networks, errors = status_server.parse_networks(["10.0.0.0/8", "lab-net"])
    assert len(networks) == 1
    assert errors == [
        "isaac_sim_status_server_allow: 'lab-net' is not a network. Fix: write it as CIDR, "
        "e.g. 10.20.0.0/16, or a single address."
    ]


def test_an_instance_s_logs_go_to_the_networks_named_for_them_alone():
    asked = []

    def logs(instance):
        asked.append(instance)
        if instance == 7:
            raise OSError("journalctl failed")
        return f"2026-11-27T09:00:00+0000 host isaac-sim-{instance}: ready\n".encode()

    # not given: nobody gets them, though the status itself is there
    with serving(lambda: {"ok": 1}, logs=logs) as (url, _cache):
        code, _h, body = call(url + "/logs/1")
        assert code == 403 and b"isaac_sim_status_server_logs_allow" in body and asked == []
        assert call(url + "/status")[0] == 200
    with serving(lambda: {"ok": 1}, logs=logs, logs_allow=["10.9.9.9/32"]) as (url, _cache):
        assert call(url + "/logs/1")[0] == 403 and asked == []
    with serving(lambda: {"ok": 1}, logs=logs, logs_allow=["127.0.0.1/32"]) as (url, _cache):
        code, headers, body = call(url + "/logs/3")
        assert (code, body) == (200, b"2026-11-27T09:00:00+0000 host isaac-sim-3: ready\n")
        assert headers["Content-Type"] == "text/plain; charset=utf-8" and asked == [3]
        # instance numbers only; a journal that cannot be read is said, and the server goes on
        for path in ("/logs/100", "/logs/x", "/logs/1/../../status", "/logs/"):
            assert call(url + path)[0] == 404, path
        assert call(url + "/logs/7")[0] == 503 and call(url + "/logs/3")[0] == 200


def test_the_journal_is_asked_for_the_unit_s_last_lines_as_plain_text():
    assert status_server.journal_argv("isaac-sim@2.service") == [
        "journalctl",
        "-u",
        "isaac-sim@2.service",
        "-n",
        "200",
        "-o",
        "short-iso",
        "--no-pager",
        "-q",
    ]
    _n, errors = status_server.parse_networks(["x"], "isaac_sim_status_server_logs_allow")
    assert errors[0].startswith("isaac_sim_status_server_logs_allow: 'x' is not a network. Fix:")


# a journal that grows: a line now, one every 0.2 s after (as journalctl -f prints them)
GROWING = "import sys, time\nfor i in range(1000):\n    print(f'line {i}', flush=True)\n    time.sleep(0.2)\n"
# journalctl -f's start: its last lines in one write, then quiet (once the server waits on the pipe)
BURST = (
    "import os, time\ntime.sleep(0.3)\n"
    "os.write(1, ''.join(f'old {i}\\n' for i in range(20)).encode())\ntime.sleep(60)\n"
)


def journals(script: str):
    """(follow, the processes it started): each followed journal a Python process running script."""
    procs = []

    def follow(instance):
        procs.append(subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE))
        return procs[-1]

    return follow, procs


def following(url: str, n: int, timeout: float = 10) -> socket.socket:
    """A client that asked the server at url to follow instance n's journal."""
    client = socket.create_connection(("127.0.0.1", int(url.rsplit(":", 1)[1])), timeout=timeout)
    client.sendall(f"GET /logs/{n}?follow=1 HTTP/1.0\r\n\r\n".encode())
    return client


def test_a_followed_journal_streams_new_lines_and_its_process_ends_with_the_client():
    follow, procs = journals(GROWING)
    with serving(lambda: {"ok": 1}, logs=lambda n: b"", logs_allow=["127.0.0.1/32"], follow=follow) as (url, _c):
        with following(url, 2) as client:
            got = b""
            while got.count(b"line ") < 3:
                got += client.recv(4096)
            assert got.startswith(b"HTTP/1.0 200 ") and b"line 0\nline 1\n" in got
        # the client went: the journal's process ends within the poll (1 s), not at the next line or the hour
        procs[0].wait(timeout=5)
    # not for the networks the logs are not for
    with serving(lambda: {"ok": 1}, logs=lambda n: b"", logs_allow=["10.9.9.9/32"], follow=follow) as (url, _c):
        assert call(url + "/logs/1?follow=1")[0] == 403


def test_followers_are_bounded():
    follow, started = journals(GROWING)
    with serving(lambda: {"ok": 1}, logs=lambda n: b"", logs_allow=["127.0.0.1/32"], follow=follow) as (url, _c):
        clients = []
        for _n in range(status_server.FOLLOWERS):
            client = following(url, 0)
            assert client.recv(64).startswith(b"HTTP/1.0 200")
            clients.append(client)
        code, _h, body = call(url + "/logs/0?follow=1")
        assert code == 503 and b"busy" in body
        for client in clients:
            client.close()
        for proc in started:
            proc.wait(timeout=5)
        # their places are free again
        with following(url, 0) as client:
            assert client.recv(64).startswith(b"HTTP/1.0 200")
    assert status_server.journal_argv("u", 20, follow=True)[-1] == "-f"


def test_a_burst_of_lines_reaches_the_client_at_once_and_a_client_that_keeps_sending_is_cut():
    follow, procs = journals(BURST)
    with serving(lambda: {"ok": 1}, logs=lambda n: b"", logs_allow=["127.0.0.1/32"], follow=follow) as (url, _c):
        with following(url, 0, timeout=3) as client:
            got = b""
            while b"old 19" not in got:
                got += client.recv(65536)  # journalctl's last lines together: all of them, not one
        procs[0].wait(timeout=5)
        with following(url, 0, timeout=3) as client:
            client.recv(64)
            with contextlib.suppress(OSError):
                client.sendall(b"x" * 200000)
            procs[1].wait(timeout=5)
