"""The front door as the fleet's gateway: on a host of its own (the mirror's host, no instance on
it), in front of the three hosts' status endpoints and the first host's web viewers, reached from
this machine as a browser outside the fleet would reach it, and its TURN relay carrying a host's
stream to a peer that can reach nothing but the gateway's TLS port.

Runs after the fleet's other modules but test_whoever_asks.py (file order), which goes on with the
front door it leaves running (destroy follows; its removal is tests/integration/instances'
test_front_door's). Its deploy of the first host
asks for a web viewer beside each instance, lets the host's signal and viewer ports answer the
gateway alone and gives its journal to the gateway (isaac_sim_status_server_logs_allow); after
test_unwanted_traffic.py, which left those viewers, the deploy changes the firewall and the
status endpoint and restarts no instance. The third host runs two instances by then (that
module's firewalld deploy scales it down), so the fixture waits for the first host's four alone.
"""

from __future__ import annotations

import json
import os
import re
import subprocess

import pytest
import testbed
from browser import chromium, console_errors
from fleethosts import PLAIN, all_ready, hosts, ip, playbook, playbook_argv, probe, sh, squash
from frontdoor import UNITS, ca_dir, check_a_stream_from_outside_the_lan, door_inventory, request, session, settings
from selenium.common.exceptions import WebDriverException
from test_stream_addresses import VIEWER, viewer_image
from testbed import ROOT

DOOR = "isaacsim-mirror-1"
SIGNAL = 49100
# the first host's viewers on the gateway: front_door_viewer_port_base + 100 x its place (0) + N
DOOR_VIEWER = 20000


@pytest.fixture(scope="module")
def fleet():
    found = hosts()
    testbed.wait_for(lambda: all_ready(found[0]), timeout=240, what=f"{found[0]} ready")
    return found


def front_door(extra: dict, limit: str | None = None, name: str = "front_door.yml") -> subprocess.CompletedProcess:
    argv = playbook_argv(name, extra, limit) + ["-i", str(door_inventory(DOOR))]
    return subprocess.run(
        argv, capture_output=True, text=True, env=dict(os.environ, **PLAIN), timeout=900, cwd=ROOT, check=False
    )


def ok(run: subprocess.CompletedProcess) -> subprocess.CompletedProcess:
    assert run.returncode == 0, squash(run.stdout + run.stderr)[-3000:]
    return run


def test_one_gateway_serves_every_host_and_its_viewers_behind_its_login(fleet, tmp_path):
    door, first, second = ip(DOOR), fleet[0], fleet[1]
    # the first host's viewers and signalling answer the gateway alone; its journal goes to it too
    ok(
        playbook(
            "deploy.yml",
            {
                "isaac_sim_web_viewer_image": viewer_image(first),
                "isaac_sim_allowed_networks_by_port": {"signal": [f"{door}/32"], "web_viewer": [f"{door}/32"]},
                "isaac_sim_status_server_logs_allow": [f"{door}/32"],
            },
            limit=first,
        )
    )
    testbed.wait_for(lambda: all_ready(first), timeout=240, what=f"{first} ready")
    direct = [("tcp", SIGNAL + 1, ""), ("tcp", VIEWER + 1, "/stream-config.js")]

    def answers(where: str) -> bool:
        got = probe(where, ip(first), direct)
        return got[f"tcp/{SIGNAL + 1}"].startswith("isaac-sim-standin signal") and " 200" in got[f"tcp/{VIEWER + 1}"]

    # a host that is not the front door reaches neither; the front door's host reaches both
    assert set(probe(second, ip(first), direct).values()) == {"timeout"}
    testbed.wait_for(lambda: answers(DOOR), timeout=120, what=f"{first}'s viewer to answer the gateway")

    ok(front_door(settings(front_door_server_name=door)))
    operator = session(door, "olga", "op-secret")
    for host in fleet:
        path = f"/hosts/{host}/status"
        # no session: the login page; with one: that host's own answer, read by the gateway
        assert request(door, "GET", path)[0].status == 302
        response, data, _v = request(door, "GET", path, cookie=operator)
        assert response.status == 200, data[:300]
        assert json.loads(data)["host"] == host, host
    viewer = session(door, "vic", "view-secret")
    check_the_logs(door, first, operator, viewer)
    in_chromium(door, first, fleet, tmp_path / "report")
    # a host's stream reaches a peer that can reach only the gateway's TLS port, relayed by the gateway
    check_a_stream_from_outside_the_lan(door, operator, first, (ip(first), 47998 + 1))

    again = ok(front_door(settings(front_door_server_name=door)))
    assert re.search(rf"{DOOR}\s*:.*changed=0", again.stdout), again.stdout[-2000:]
    # a run that could not read a host behind it changes nothing and says which and why
    conf = sh(DOOR, "cat /etc/isaac-sim/front-door/nginx.conf")
    limited = front_door(settings(front_door_server_name=door), limit=f"{DOOR},{fleet[0]},{fleet[1]}")
    assert limited.returncode != 0
    assert f"front_door_hosts: {fleet[2]} did not say where they serve their status" in squash(
        limited.stdout + limited.stderr
    )
    assert sh(DOOR, "cat /etc/isaac-sim/front-door/nginx.conf") == conf
    assert request(door, "GET", f"/hosts/{fleet[2]}/status", cookie=operator)[0].status == 200
    # no run with front_door_state absent (destroy follows): tests/integration/instances' test_front_door ends
    # with one (units gone, 443 and 5349 closed), test_web_viewer_front_door with one (the viewers' ports closed)


def check_the_logs(door: str, first: str, operator: str, viewer: str) -> None:
    """An instance's journal through the gateway: an operator's, never a viewer's."""
    path = f"/operator/hosts/{first}/logs/1"
    response, data, _v = request(door, "GET", path, cookie=operator)
    assert response.status == 200, data[:300]
    last = data.decode().strip().splitlines()[-1]
    assert last and last in sh(first, "journalctl -u isaac-sim@1.service -o short-iso --no-pager -q -n 400")
    assert request(door, "GET", path, cookie=viewer)[0].status == 403
    in_journal(DOOR, UNITS[1], f"refused user=vic path='{path}'")


def in_chromium(door: str, first: str, fleet: list, report) -> None:
    """The dashboard and a viewer through the gateway, in headless Chromium trusting only the
    collection's CA: the login first (a wrong password refused and written down), then every host
    live behind the gateway, each instance's entrance, and a viewer of the first host whose page
    signals to the gateway over WSS, which relays it to the stand-in's signal port."""
    ok(front_door({"fleet_report_dir": str(report), "fleet_report_refresh": 1}, name="status.yml"))
    status = json.loads((report / "status.json").read_text())
    # an entrance is a web viewer's: the first host's instances alone have one
    entrances = sorted(i["entrance"] for h in status["hosts"] for i in h["instances"] if i.get("entrance"))
    assert entrances == [f"https://{door}/viewers/{first}/{i}/" for i in range(4)]
    port = DOOR_VIEWER + 1
    with chromium(trust_ca=ca_dir() / "ca.crt") as driver:

        def body(name):
            # a page is still there a moment after a click, then goes: ask again
            try:
                return driver.find_element("tag name", "body").get_attribute(name)
            except WebDriverException:
                return None

        def log_in(user, password):
            driver.find_element("name", "user").send_keys(user)
            driver.find_element("name", "password").send_keys(password)
            driver.find_element("css selector", "button[type=submit]").click()

        driver.get(f"https://{door}/dashboard.html")
        testbed.wait_for(lambda: "/login?next=/dashboard.html" in driver.current_url, timeout=15, what="the login")
        log_in("vic", "wrong")
        testbed.wait_for(lambda: "Wrong user name or password" in driver.page_source, timeout=10, what="the refusal")
        refusal = "Failed to load resource: the server responded with a status of 401 (Unauthorized)"
        assert [e["message"] for e in console_errors(driver)] == [f"https://{door}/login - {refusal}"]
        log_in("vic", "view-secret")
        testbed.wait_for(lambda: driver.current_url == f"https://{door}/dashboard.html", timeout=10, what="the page")
        sections = driver.find_elements("css selector", "section.host")
        assert len(sections) == len(fleet)
        for section in sections:
            testbed.wait_for(lambda s=section: s.get_attribute("data-live") == "ok", timeout=15, what="every host live")
        links = driver.find_elements("css selector", ".instance-card a[data-kind=entrance]")
        assert sorted(a.get_attribute("href") for a in links) == entrances

        driver.get(f"https://{door}/viewers/{first}/1/")
        testbed.wait_for(lambda: body("data-configured") == "yes", timeout=15, what="the viewer")
        assert driver.current_url == f"https://{door}:{port}/"
        # signalling to the gateway over WSS; the media still from the instance's host
        assert driver.find_element("id", "signal").text == f"wss://{door}:{port}/"
        assert driver.find_element("id", "media").text == f"{ip(first)}:47999/udp"
        driver.get(f"https://{door}:{port}/?connect")
        testbed.wait_for(lambda: body("data-signalling") == "open", timeout=15, what="the signalling")
        assert console_errors(driver) == []
    in_journal(DOOR, UNITS[1], "login refused user=vic")
    # the stand-in's signal port on the first host saw it come through the gateway, from the viewer's page
    seen = f"signalling from {door}, GET /, Origin https://{door}:{port}"
    in_journal(first, "isaac-sim@1", f"streaming session started ({seen})")


def in_journal(host: str, unit: str, line: str) -> None:
    """The unit's journal on host has the line, once journald has taken it in."""
    testbed.wait_for(
        lambda: line in sh(host, f"journalctl -u {unit} --no-pager -o cat"), timeout=10, what=f"{line!r} on {host}"
    )
