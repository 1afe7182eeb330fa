"""The 6.x web viewers behind the front door (per-host mode: the door on the test host itself),
after test_web_viewer.py left a viewer beside each instance.

A headless Chromium that trusts only the collection's CA: the entrance asks for the login; after it
the viewer's page comes over HTTPS on its door port, and the page signals back to the front door
over WSS, which relays it to the stand-in's signal port (the stand-in writes who signalled, from
where and from which page). The direct viewer and signal ports then answer the front door alone.
The TURN relay: credentials from a login carry a datagram over TLS to an instance's stream port
and its answer back (the stand-in answers each datagram); nowhere else, and never with credentials
expired or forged. A whole WebRTC stream through the relay (check_a_stream_from_outside_the_lan), and
a second door run with the viewers that changes nothing, are the fleet's gateway test's
(tests/integration/fleet/test_viewers_through_the_gateway.py, the same helper and role); the door's
run without viewers changing nothing, test_front_door's.
"""

import base64
import hashlib
import hmac
import json
import os
import socket
import time

import pytest
import testbed
from aioice.stun import TransactionFailed
from browser import chromium, console_errors
from frontdoor import (
    UNITS,
    ca_dir,
    door_inventory,
    log_in,
    relay_credentials,
    relayed_exchange,
    request,
    session,
    settings,
)
from selenium.common.exceptions import WebDriverException
from testbed import INSTANCES, sh, wait_for

BASE = 20000
UPGRADE = {
    "Upgrade": "websocket",
    "Connection": "Upgrade",
    "Sec-WebSocket-Version": "13",
    "Sec-WebSocket-Key": base64.b64encode(os.urandom(16)).decode(),
}


def ok(result):
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    return result


def door(host, **over):
    return testbed.run_playbook(
        host, settings(**over), extra_inventory=door_inventory(testbed.name(host)), playbook="playbooks/front_door.yml"
    )


def reaches(address, port) -> bool:
    try:
        with socket.create_connection((address, port), timeout=3):
            return True
    except OSError:
        return False


def test_viewers_open_behind_the_login_signal_over_wss_through_the_door_and_answer_it_alone(host, tmp_path):
    address, name = testbed.host_ip(host), testbed.name(host)
    # a viewer beside each instance, whose page and signal ports answer the front door only (it is
    # this host: its own traffic is local)
    only_door = {"signal": [f"{address}/32"], "web_viewer": [f"{address}/32"]}
    viewer = testbed.registry_image(host, "6.0.1").replace("isaac-sim-standin:6.0.1", "isaac-sim-web-viewer:2.1.5")
    ok(
        testbed.run_playbook(
            host, {"isaac_sim_web_viewer_image": viewer, "isaac_sim_allowed_networks_by_port": only_door}
        )
    )
    testbed.all_ready(host)
    assert not reaches(address, 8211) and not reaches(address, 49101)
    ok(door(host, front_door_server_name=address))
    try:
        assert all(reaches(address, BASE + i) for i in range(INSTANCES))

        # no session: neither the page nor its signalling, whatever the Origin
        response, _d, _v = request(address, "GET", "/", port=BASE + 1)
        assert response.status == 302
        assert response.getheader("Location") == f"https://{address}/login?next=/viewers/{name}/1/"
        origin = {"Origin": f"https://{address}:{BASE + 1}"}
        response, _d, _v = request(address, "GET", "/", port=BASE + 1, headers=dict(UPGRADE, **origin))
        assert response.status in (302, 401)
        cookie = session(address, "vic", "view-secret")
        # another site's page cannot open it with the person's session
        evil = {"Origin": "https://evil.example"}
        response, _d, _v = request(address, "GET", "/", cookie=cookie, port=BASE + 1, headers=dict(UPGRADE, **evil))
        assert response.status == 403

        with chromium(trust_ca=ca_dir() / "ca.crt") as driver:
            driver.get(f"https://{address}/viewers/{name}/1/")
            wait_for(lambda: "/login?next=/viewers/" in driver.current_url, timeout=15, what="the login page")
            log_in(driver, "vic", "view-secret")

            def body(name):
                # the login page is still there a moment after the click, then goes: ask again
                try:
                    return driver.find_element("tag name", "body").get_attribute(name)
                except WebDriverException:
                    return None

            wait_for(lambda: body("data-configured") == "yes", timeout=15, what="the viewer")
            assert driver.current_url == f"https://{address}:{BASE + 1}/"
            # signalling to the front door over WSS; the media still to the instance
            assert driver.find_element("id", "signal").text == f"wss://{address}:{BASE + 1}/"
            assert driver.find_element("id", "media").text == f"{address}:47999/udp"
            driver.get(f"https://{address}:{BASE + 1}/?connect")
            wait_for(lambda: body("data-signalling") == "open", timeout=15, what="the signalling")
            assert console_errors(driver) == []
            driver.save_screenshot(str(testbed.ROOT / "tests" / "output" / "front-door-viewer.png"))
            check_the_entrances(host, address, driver, tmp_path / "report")
        # the stand-in's signal port saw it come from the front door, from the viewer's own page
        log = sh(host, "journalctl -u isaac-sim@1 --no-pager -o cat").stdout
        seen = f"signalling from {address}, GET /, Origin https://{address}:{BASE + 1}"
        assert f"streaming session started ({seen})" in log
        door_log = sh(host, f"journalctl -u {UNITS[0]} --no-pager -o cat").stdout
        assert "user=vic" in door_log

        check_the_relay(host, address, cookie)
    finally:
        gone = ok(door(host, front_door_server_name=address, front_door_state="absent"))
    assert not any(reaches(address, BASE + i) for i in range(INSTANCES)), gone.stdout[-2000:]
    assert not reaches(address, 5349) and "inactive" in sh(host, f"systemctl is-active {UNITS[2]} || true").stdout


def check_the_entrances(host, address, driver, report):
    """status.yml gives each instance its entrance, in status.json and on the door's dashboard
    (where a viewer, as vic is, sees the entrances and no direct address)."""
    name = testbed.name(host)
    run = testbed.run_playbook(
        host,
        {"fleet_report_dir": str(report), "fleet_report_refresh": 0},
        extra_inventory=door_inventory(name),
        playbook="playbooks/status.yml",
    )
    ok(run)
    instances = json.loads((report / "status.json").read_text())["hosts"][0]["instances"]
    wanted = {i: f"https://{address}/viewers/{name}/{i}/" for i in range(INSTANCES)}
    assert {i["id"]: i.get("entrance") for i in instances} == wanted
    driver.get(f"https://{address}/dashboard.html")
    links = "css selector", ".instance-card a[data-kind=entrance]"
    wait_for(lambda: len(driver.find_elements(*links)) == INSTANCES, timeout=15, what="the entrances")
    assert sorted(a.get_attribute("href") for a in driver.find_elements(*links)) == sorted(wanted.values())
    wait_for(lambda: driver.find_element("tag name", "body").get_attribute("data-role") == "viewer", timeout=10)
    assert len(driver.find_elements("css selector", ".instance-card [data-kind]")) == INSTANCES
    assert console_errors(driver) == []


def check_the_relay(host, address, cookie):
    creds = relay_credentials(address, cookie)
    [server] = creds["iceServers"]
    # good until the session ends: 8 h after the login, a moment ago
    assert server["urls"] == [f"turns:{address}:5349?transport=tcp"] and 8 * 3600 - 600 < creds["ttl"] <= 8 * 3600
    user, password = server["username"], server["credential"]
    expires, name = user.split(":", 1)
    assert name == "vic" and int(expires) > time.time() + 7 * 3600
    # an instance's stream port answers through the relay, from a relay port of the fixed range
    relayed, answer = relayed_exchange(address, 5349, user, password, (address, 47998 + 2))
    assert 50000 <= relayed[1] <= 50199
    assert answer is not None and answer.startswith(b"isaac-sim-standin stream ")
    # the relay is no way into the rest of the network: another address gets nothing through
    controller = sh(host, "ip route | awk '/default/ {print $3}'").stdout.strip()
    with pytest.raises(TransactionFailed, match="403"):
        relayed_exchange(address, 5349, user, password, (controller, 9))
    # expired, or not the relay's own: refused
    secret = sh(host, "cat /etc/isaac-sim/front-door/turn.secret").stdout.strip().encode()
    old_name = f"{int(time.time()) - 60}:vic"
    old = base64.b64encode(hmac.new(secret, old_name.encode(), hashlib.sha1).digest()).decode()
    for bad_user, bad_password in ((old_name, old), (user, "forged")):
        with pytest.raises(TransactionFailed, match="401"):
            relayed_exchange(address, 5349, bad_user, bad_password, (address, 47998 + 2))
    # TLS only: no plain TURN listener
    assert not reaches(address, 3478)
    journal = sh(host, f"journalctl -u {UNITS[1]} --no-pager -o cat").stdout
    assert "turn credentials user=vic from=" in journal
