"""The front door as the fleet's gateway: on a host of its own (the mirror's host, no instance on
it), in front of the three hosts' status endpoints, reached from this machine as a browser
outside the fleet would reach it, and its TURN relay carrying a host's stream to a peer that can
reach nothing but the gateway's TLS port."""

from __future__ import annotations

import json
import os
import subprocess

import pytest
from fleethosts import PLAIN, ip, playbook_argv, ready_fleet, sh, squash
from frontdoor import check_a_stream_from_outside_the_lan, door_inventory, request, session, settings
from testbed import ROOT

DOOR = "isaacsim-mirror-1"


@pytest.fixture(scope="module")
def fleet():
    return ready_fleet()


def front_door(extra: dict, limit: str | None = None) -> subprocess.CompletedProcess:
    argv = playbook_argv("front_door.yml", extra, limit) + ["-i", str(door_inventory(DOOR))]
    return subprocess.run(
        argv, capture_output=True, text=True, env=dict(os.environ, **PLAIN), timeout=900, cwd=ROOT, check=False
    )


def test_one_gateway_serves_every_host_behind_its_login_and_never_drops_one_it_could_not_read(fleet):
    door = ip(DOOR)
    first = front_door(settings(front_door_server_name=door))
    assert first.returncode == 0, squash(first.stdout + first.stderr)[-3000:]
    try:
        operator = session(door, "olga", "op-secret")
        for host in fleet:
            path = f"/hosts/{host}/status"
            # no session: the login page; with one: that host's own answer, read by the gateway
            assert request(door, "GET", path)[0].status == 302
            response, data, _v = request(door, "GET", path, cookie=operator)
            assert response.status == 200, data[:300]
            assert json.loads(data)["host"] == host, host
        # a host's stream reaches a peer that can reach only the gateway's TLS port, relayed by the gateway
        check_a_stream_from_outside_the_lan(door, operator, fleet[0], (ip(fleet[0]), 47998 + 1))
        # a run that could not read a host behind it changes nothing and says which and why
        conf = sh(DOOR, "cat /etc/isaac-sim/front-door/nginx.conf")
        limited = front_door(settings(front_door_server_name=door), limit=f"{DOOR},{fleet[0]},{fleet[1]}")
        assert limited.returncode != 0
        assert f"front_door_hosts: {fleet[2]} did not say where they serve their status" in squash(
            limited.stdout + limited.stderr
        )
        assert sh(DOOR, "cat /etc/isaac-sim/front-door/nginx.conf") == conf
        assert request(door, "GET", f"/hosts/{fleet[2]}/status", cookie=operator)[0].status == 200
    finally:
        gone = front_door(settings(front_door_state="absent"))
    assert gone.returncode == 0, squash(gone.stdout + gone.stderr)[-3000:]
    assert "isaac-sim-front-door" not in sh(
        DOOR, "systemctl list-unit-files 'isaac-sim-front-door*' --no-legend || true"
    )
