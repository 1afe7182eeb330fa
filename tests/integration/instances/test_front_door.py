"""The front door (roles/front_door) on the test host: HTTPS with the collection's CA, a login in
front of the host's status endpoint, roles, the journal, rate limiting, and its removal.

The requests come from this machine (the controller), as a browser outside the host would send
them, through Python's own HTTP client with the CA the role made (nothing trusts it otherwise).
"""

import contextlib
import hashlib
import http.client
import json
import os
import re
import shlex
import socket
import ssl
import subprocess
import threading
import time
import urllib.error
import urllib.request

import pytest
import testbed
from browser import chromium, console_errors
from frontdoor import (
    UNITS,
    as_person,
    ca_dir,
    check_the_action_channel,
    door_inventory,
    log_in,
    login,
    request,
    session,
    settings,
)
from selenium.common.exceptions import (
    NoAlertPresentException,
    NoSuchElementException,
    StaleElementReferenceException,
)
from testbed import INSTANCES, sh, wait_for


def ok(result):
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    return result


def run(host, **over):
    inventory = door_inventory(testbed.name(host))
    return testbed.run_playbook(host, settings(**over), extra_inventory=inventory, playbook="playbooks/front_door.yml")


def journal(host, unit):
    return sh(host, f"journalctl -u {unit} --no-pager -o cat").stdout


def in_journal(host, unit, line):
    """The unit's journal has the line, once journald has taken it in (it reads the unit's output
    on its own time: a line written a moment ago may not be there yet)."""
    wait_for(lambda: line in journal(host, unit), timeout=10, what=f"{line!r} in the journal of {unit}")


# the stand-in's Documents (6.x: NVIDIA's mount for the isaac-sim user), a file vic saves there, and the
# door's store of each person's files (front_door_sim_files_dir)
DOCUMENTS, MARKER, FILES_DIR = "/isaac-sim/Documents", "vic-marker.txt", "/var/lib/isaac-sim-front-door/files"
# the sessions' figures (front_door_metrics_textfile_dir's default)
SESSIONS_PROM = "/var/lib/prometheus/node-exporter/isaac_sim_sessions.prom"


def door_services_killed_keep_sessions_and_places(host, address, pages):
    """The login and API services killed (SIGKILL, as a crash) while four hold instances and one waits:
    systemd starts them again, and every session and place in the queue is as it was (SQLite on disk).
    The open pages' polls meanwhile fail (nginx's 500 or 502 for the service away), and nothing else."""
    olga = session(address, "olga", "op-secret")

    def held_and_queued():
        _code, everything = as_person(address, "GET", "/api/sessions", olga)
        held = sorted((s["user"], s["instance"], s["state"]) for s in everything["sessions"])
        return held, [q["user"] for q in everything["queue"]]

    before = held_and_queued()
    assert len(before[0]) == INSTANCES and before[1] == ["val"], before
    killed = (UNITS[1], UNITS[3])
    runs = {unit: testbed.unit_show(host, unit)["InvocationID"] for unit in killed}
    for unit in killed:
        sh(host, f"systemctl kill -s SIGKILL {unit}")
    wait_for(lambda: held_and_queued() == before, timeout=60, what="the sessions and the queue after the kill")
    # each a new run of its unit (started again by systemd), not one that outlived its kill
    assert all(testbed.unit_show(host, unit)["InvocationID"] != runs[unit] for unit in killed)
    away = re.compile(
        rf"^https://{re.escape(address)}/(api/sessions|session)\S* - Failed to load resource: the server "
        r"responded with a status of 50[02] "
    )
    time.sleep(3)  # a poll (every 2 s) after the services came back: the pages read them again
    for page in pages:
        errors = console_errors(page)
        assert all(away.match(e["message"]) for e in errors), errors


def simulator_in_chromium(driver, host, address):
    """People at once: three take three instances, vic's page gets the last one with its time left, val's
    page waits first in the queue; vic ends it, and val's page gets that instance, restarted (reset)
    first. Each page says how its session ended. vic's files go with vic: gone from the instance val gets,
    back in vic's next session."""
    others = {name: session(address, name, "view-secret") for name in ("ana", "ben", "cy")}
    held = [as_person(address, "POST", "/api/sessions", cookie, {}) for cookie in others.values()]
    assert [code for code, _s in held] == [201] * 3, held
    assert len({s["instance"] for _c, s in held}) == 3
    driver.get(f"https://{address}/simulator.html")
    body = driver.find_element("tag name", "body")
    wait_for(lambda: body.get_attribute("data-ready") == "yes", timeout=15, what="the simulator page")
    assert body.get_attribute("data-state") == "none", driver.find_element("id", "state").text
    driver.find_element("id", "ask").click()
    wait_for(lambda: body.get_attribute("data-state") == "active", timeout=15, what="a simulator for vic")
    state = driver.find_element("id", "state").text
    assert state.startswith(f"Your simulator: {testbed.name(host)}, instance "), state
    n = int(state.rsplit(" ", 1)[1].rstrip("."))
    assert n not in {s["instance"] for _c, s in held}
    assert driver.find_element("id", "left").text.startswith("Time left: 3:59:")
    driver.save_screenshot(str(testbed.ROOT / "tests" / "output" / "front-door-simulator.png"))
    before = testbed.container_id(host, f"isaac-sim-{n}")
    # what vic saves in the simulator's Documents (as the container's own user) follows vic, never val
    sh(host, f"docker exec isaac-sim-{n} sh -c 'mkdir -p {DOCUMENTS}/work && echo vic > {DOCUMENTS}/work/{MARKER}'")
    with chromium(trust_ca=ca_dir() / "ca.crt") as other:
        other.get(f"https://{address}/simulator.html")
        wait_for(lambda: "/login?next=/simulator.html" in other.current_url, timeout=15, what="val's login page")
        log_in(other, "val", "view-secret")
        wait_for(
            lambda: other.current_url == f"https://{address}/simulator.html"
            and other.find_element("tag name", "body").get_attribute("data-ready") == "yes",
            timeout=15,
            what="val's simulator page",
        )
        waiting = other.find_element("tag name", "body")
        other.find_element("id", "ask").click()
        wait_for(lambda: waiting.get_attribute("data-state") == "queued", timeout=15, what="val in the queue")
        assert other.find_element("id", "state").text.startswith("You are number 1 of 1 in the queue")
        door_services_killed_keep_sessions_and_places(host, address, (driver, other))
        assert other.find_element("id", "state").text.startswith("You are number 1 of 1 in the queue")
        driver.find_element("id", "end").click()
        wait_for(lambda: body.get_attribute("data-state") == "ended", timeout=120, what="vic's session to end")
        assert driver.find_element("id", "state").text == "Your session ended (ended by its holder)."
        wait_for(lambda: waiting.get_attribute("data-state") == "active", timeout=60, what="val's simulator")
        assert other.find_element("id", "state").text == f"Your simulator: {testbed.name(host)}, instance {n}."
        # the one vic had, reset (a fresh container) before val got it, with none of vic's files
        assert testbed.container_id(host, f"isaac-sim-{n}") not in ("", before)
        assert sh(host, f"docker exec isaac-sim-{n} ls -A {DOCUMENTS}").stdout.strip() == ""
        other.find_element("id", "end").click()
        wait_for(lambda: waiting.get_attribute("data-state") == "ended", timeout=120, what="val's session to end")
        assert console_errors(other) == []
    # vic's files are on the door, the person's alone (0600, named by a hash of the name), and no longer
    # on the host once the door took them (val's too, at the door's next look)
    assert sh(host, f"stat -c %a {FILES_DIR}/{hashlib.sha256(b'vic').hexdigest()}.tar").stdout == "600\n"
    wait_for(lambda: sh(host, "ls -A /var/lib/isaac-sim/files").stdout.strip() == "", timeout=30, what="no stash left")
    # and back in vic's next session, whichever instance it is
    driver.find_element("id", "ask").click()
    wait_for(lambda: body.get_attribute("data-state") == "active", timeout=120, what="vic's next simulator")
    m = int(driver.find_element("id", "state").text.rsplit(" ", 1)[1].rstrip("."))
    assert sh(host, f"docker exec isaac-sim-{m} cat {DOCUMENTS}/work/{MARKER}").stdout == "vic\n"
    driver.find_element("id", "end").click()
    wait_for(lambda: body.get_attribute("data-state") == "ended", timeout=120, what="vic's next session to end")
    for (_c, s), cookie in zip(held, others.values()):
        assert as_person(address, "DELETE", s["url"], cookie)[0] == 200
    assert console_errors(driver) == []
    testbed.all_ready(host)


def dashboard_in_chromium(host, address, tmp_path):
    report = tmp_path / "report"
    ok(
        testbed.run_playbook(
            host,
            {"fleet_report_dir": str(report), "fleet_report_refresh": 1},
            extra_inventory=door_inventory(testbed.name(host)),
            playbook="playbooks/status.yml",
        )
    )
    page = (report / "status-front-door.html").read_text()
    assert f'data-status-url="/hosts/{testbed.name(host)}/status"' in page
    # the report says where the front door is, when its certificate ends and whether its relay runs
    [door] = json.loads((report / "status.json").read_text())["front_doors"]
    assert (door["url"], door["relay"], door["healthy"]) == (f"https://{address}/", "active", True), door
    assert 823 <= door["certificate_days_left"] <= 825, door
    assert (
        f"front door {testbed.name(host)}: https://{address}/, certificate until "
        in (report / "status.txt").read_text()
    )
    with chromium(trust_ca=ca_dir() / "ca.crt") as driver:
        driver.get(f"https://{address}/dashboard.html")
        # no session: the login page, over a certificate the browser trusts (else an interstitial)
        wait_for(lambda: "/login?next=/dashboard.html" in driver.current_url, timeout=15, what="the login page")

        log_in(driver, "vic", "wrong")
        wait_for(lambda: "Wrong user name or password" in driver.page_source, timeout=10, what="the refusal")
        # the refusal's own 401 is the one console error so far
        refusal = "the server responded with a status of 401 (Unauthorized)"
        assert [e["message"] for e in console_errors(driver)] == [
            f"https://{address}/login - Failed to load resource: {refusal}"
        ]
        log_in(driver, "vic", "view-secret")
        wait_for(lambda: driver.current_url == f"https://{address}/dashboard.html", timeout=10, what="the dashboard")
        section = driver.find_element("css selector", "section.host")
        # live: the page reads the host's status through the front door, behind the same login
        wait_for(lambda: section.get_attribute("data-live") == "ok", timeout=15, what="the page to read the host")
        assert len(driver.find_elements("css selector", ".instance-card")) == INSTANCES
        line = driver.find_element("css selector", "p.front-door").text
        assert "certificate until" in line and "relay active (turns:" in line, line
        # a viewer sees no instance's direct address, an operator does
        wait_for(lambda: driver.find_element("tag name", "body").get_attribute("data-role") == "viewer", timeout=10)
        direct = "css selector", ".instance-card [data-kind]:not([data-kind=entrance]):not([data-kind=logs])"
        assert driver.find_elements(*direct) == []
        assert driver.find_elements("css selector", "button.follow") == []
        assert driver.find_elements("css selector", ".actions button") == []
        assert console_errors(driver) == []
        driver.save_screenshot(str(testbed.ROOT / "tests" / "output" / "front-door-dashboard.png"))
        simulator_in_chromium(driver, host, address)
        driver.get(f"https://{address}/logout")
        # the page kept nothing in the browser's cache (Cache-Control: no-store): the login again
        driver.get(f"https://{address}/dashboard.html")
        wait_for(lambda: "/login?next=/dashboard.html" in driver.current_url, timeout=15, what="the login page")
        log_in(driver, "olga", "op-secret")
        wait_for(lambda: driver.current_url == f"https://{address}/dashboard.html", timeout=10, what="the dashboard")
        wait_for(lambda: driver.find_elements(*direct), timeout=15, what="the direct addresses")
        assert driver.find_element("tag name", "body").get_attribute("data-role") == "operator"
        # and each instance's journal, through the door
        hrefs = [a.get_attribute("href") for a in driver.find_elements("css selector", "a[data-kind=logs]")]
        assert sorted(hrefs) == [
            f"https://{address}/operator/hosts/{testbed.name(host)}/logs/{i}" for i in range(INSTANCES)
        ]
        # and followed live in the page, through the fleet's API; stopped by the same button
        card = driver.find_element("css selector", '.instance-card[data-instance="1"]')
        card.find_element("css selector", "button.follow").click()
        wait_for(lambda: card.get_attribute("data-following") == "yes", timeout=10, what="the journal to be followed")
        journal = card.find_element("css selector", "pre.journal")
        wait_for(lambda: len(journal.text.splitlines()) >= 5, timeout=20, what="the journal's lines in the page")
        last = journal.text.splitlines()[-1]
        assert last in sh(host, "journalctl -u isaac-sim@1.service -o short-iso --no-pager -q -n 400").stdout
        # a new line of the instance's journal reaches the page (measured; the goal is 2 s)
        marker = f"console-marker-{time.time_ns()}"
        sh(host, f"printf 'MESSAGE={marker}\\nOBJECT_SYSTEMD_UNIT=isaac-sim@1.service\\n' | logger --journald")
        began = time.monotonic()
        wait_for(lambda: marker in journal.text, timeout=15, interval=0.1, what="the new journal line in the page")
        print(f"a new journal line reached the page in {time.monotonic() - began:.2f} s")
        card.find_element("css selector", "button.follow").click()
        wait_for(lambda: card.get_attribute("data-following") == "no", timeout=10, what="the journal to stop")
        assert console_errors(driver) == []
        actions_in_the_console(driver, host)
        tokens_in_the_console(driver, host, address)
    in_journal(host, UNITS[1], "login refused user=vic")


def asked(driver):
    """The page's confirmation, once it is there."""
    try:
        return driver.switch_to.alert
    except NoAlertPresentException:
        return None


def actions_in_the_console(driver, host):
    """An operator restarts an instance from its card: the progress line moves to the end, the instance
    is ready again, the host's last actions say who did it. With another instance stopped, the page
    asks before a restart that would take the host below N-1, and goes on once confirmed."""
    name = testbed.name(host)

    def run_action(card, action, confirm=False):
        card.find_element("css selector", f'.actions button[data-action="{action}"]').click()
        if confirm:
            alert = wait_for(lambda: asked(driver), timeout=20, interval=0.2, what="the confirmation")
            assert "below N-1" in alert.text, alert.text
            alert.accept()
        seen = set()

        def ended():
            line = card.find_element("css selector", "p.progress")
            seen.add(line.text)
            return line.get_attribute("data-state") in ("succeeded", "failed", "refused")

        wait_for(ended, timeout=120, interval=0.2, what=f"{action} to end")
        line = card.find_element("css selector", "p.progress")
        assert line.get_attribute("data-state") == "succeeded", line.text
        return seen

    # a person's session: the card says whose it is, and the operator ends it from there
    address = testbed.host_ip(host)
    vic = session(address, "vic", "view-secret")
    code, held = as_person(address, "POST", "/api/sessions", vic, {})
    assert code == 201, held
    art = driver.find_element("css selector", f'.instance-card[data-instance="{held["instance"]}"]')

    def text_of(css):
        try:
            return art.find_element("css selector", css).text
        except (NoSuchElementException, StaleElementReferenceException):
            return None

    wait_for(lambda: text_of("dd.f-holder") == f"session {held['id']} of vic", timeout=20, what="the card's holder")
    art.find_element("css selector", "button.end-session").click()
    alert = wait_for(lambda: asked(driver), timeout=20, interval=0.2, what="the confirmation")
    assert alert.text.startswith(f"End the session of vic on isaac-sim-{held['instance']}?"), alert.text
    alert.accept()
    wait_for(lambda: (text_of("p.progress") or "").endswith("ended by the operator olga"), timeout=20)
    wait_for(
        lambda: as_person(address, "GET", held["url"], vic)[1]["state"] == "ended",
        timeout=120,
        what="vic's session ended by the operator, its instance reset",
    )
    wait_for(lambda: text_of("dd.f-holder") is None, timeout=20, what="the card to show no holder")
    testbed.all_ready(host)

    card = driver.find_element("css selector", '.instance-card[data-instance="2"]')
    seen = run_action(card, "restart")
    # the progress line moved: more than the end was shown
    assert len(seen) >= 2 and any("%" in text for text in seen), seen
    assert testbed.instance_ready(host, 2)
    section = driver.find_element("css selector", f'section.host[data-host="{name}"]')
    last = section.find_element("css selector", "ol.last-actions")
    wait_for(lambda: "restart isaac-sim-2 by olga: succeeded" in last.text, timeout=10, what="the last actions")
    in_journal(host, "isaac-sim@2.service", "restart isaac-sim-2 by olga: succeeded")
    stopped = driver.find_element("css selector", '.instance-card[data-instance="3"]')
    run_action(stopped, "stop")
    try:
        run_action(card, "restart", confirm=True)
        run_action(stopped, "start")
    finally:  # the next tests want every instance serving, whatever became of this one
        sh(host, "systemctl start isaac-sim@3.service", check=False)
    testbed.all_ready(host)
    # the API's 412, before the confirmation, is the one resource the browser reports as failed
    assert [e["message"] for e in console_errors(driver)] == [
        f"https://{testbed.host_ip(host)}/api/hosts/{name}/instances/2/restart - Failed to load resource: "
        "the server responded with a status of 412 (Precondition Failed)"
    ]


def tokens_in_the_console(driver, host, address):
    """A person makes a token of their own in the console, shown once, which a program then uses;
    revoked in the page, it opens nothing."""
    driver.get(f"https://{address}/tokens.html")
    wait_for(lambda: driver.find_element("tag name", "body").get_attribute("data-ready") == "yes", timeout=15)
    driver.find_element("css selector", "input[name=name]").send_keys("browser")
    driver.find_element("css selector", "input[name=scope][value=act]").click()
    driver.find_element("css selector", "#make button[type=submit]").click()
    made = driver.find_element("id", "made")
    wait_for(lambda: made.text.startswith("isf_"), timeout=10, what="the token, shown once")
    token = made.text.strip()
    status_path = f"/hosts/{testbed.name(host)}/status"
    assert request(address, "GET", status_path, headers={"Authorization": f"Bearer {token}"})[0].status == 200
    row = '#tokens tr[data-name="browser"]'
    assert "read, act" in driver.find_element("css selector", row).text
    driver.find_element("css selector", f"{row} button.revoke").click()

    def state() -> str:
        # the page draws its list again after the revocation: read the row as it is now, in one call
        return driver.execute_script(f"var r = document.querySelector('{row}'); return r ? r.textContent : '';")

    wait_for(lambda: "revoked" in state(), timeout=10, what="the revocation")
    assert request(address, "GET", status_path, headers={"Authorization": f"Bearer {token}"})[0].status == 401
    in_journal(host, UNITS[1], "token made user=olga name=browser scopes=read,act days=30 from=")
    assert console_errors(driver) == []


def check_client_certificates(host, address, pki):
    """front_door_client_ca: without a certificate its CA signed, no page answers (nginx: 400); with
    one, the login page as before, and the access log names the certificate's subject."""
    pki.mkdir()

    def openssl(*args):
        subprocess.run(["openssl", *map(str, args)], check=True, capture_output=True)

    for ca in ("people-ca", "other-ca"):
        openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", 2, "-subj", f"/CN={ca}",
                "-keyout", pki / f"{ca}.key", "-out", pki / f"{ca}.crt")  # fmt: skip
    for person, ca in (("ana", "people-ca"), ("eve", "other-ca")):
        openssl("req", "-new", "-newkey", "rsa:2048", "-nodes", "-subj", f"/CN={person}",
                "-keyout", pki / f"{person}.key", "-out", pki / f"{person}.csr")  # fmt: skip
        openssl("x509", "-req", "-in", pki / f"{person}.csr", "-CA", pki / f"{ca}.crt", "-CAkey", pki / f"{ca}.key",
                "-set_serial", "0x" + os.urandom(8).hex(), "-days", 2, "-out", pki / f"{person}.crt")  # fmt: skip
    bad = run(host, front_door_server_name=address, front_door_client_ca=str(pki / "nothing.pem"))
    said = bad.stdout + bad.stderr
    assert (
        bad.returncode != 0 and f"front_door_client_ca: '{pki / 'nothing.pem'}' is not a file on the controller" in said
    )
    ok(run(host, front_door_server_name=address, front_door_client_ca=str(pki / "people-ca.crt")))
    ana, eve = ((pki / f"{p}.crt", pki / f"{p}.key") for p in ("ana", "eve"))
    assert request(address, "GET", "/login")[0].status == 400
    assert request(address, "GET", "/login", client_cert=eve)[0].status == 400
    assert request(address, "GET", "/login", client_cert=ana)[0].status == 200
    # a certificate is no login: the pages behind still ask for one
    assert request(address, "GET", f"/hosts/{testbed.name(host)}/status", client_cert=ana)[0].status == 302
    in_journal(host, UNITS[0], 'cert="CN=ana"')


def check_the_logs(host, address, viewer, operator):
    """An instance's journal through the front door: an operator gets it, a viewer does not, and
    the host gives it to the door's address alone (isaac_sim_status_server_logs_allow)."""
    name = testbed.name(host)
    logs = f"/operator/hosts/{name}/logs/1"
    assert request(address, "GET", logs, cookie=viewer)[0].status == 403
    in_journal(host, UNITS[1], f"refused user=vic path='{logs}'")
    response, data, _v = request(address, "GET", logs, cookie=operator)
    assert response.status == 200 and response.getheader("Content-Type").startswith("text/plain"), data[:300]
    last = data.decode().splitlines()[-1]
    assert last in sh(host, "journalctl -u isaac-sim@1.service -o short-iso --no-pager -q -n 400").stdout
    assert len(data.decode().splitlines()) <= 200
    # instance numbers only; not past the door's own path
    assert request(address, "GET", f"/operator/hosts/{name}/logs/100", cookie=operator)[0].status == 404
    # the host itself: not to this machine, which may read its status
    direct = urllib.request.Request(f"http://{address}:8290/logs/1")
    with pytest.raises(urllib.error.HTTPError, match="403"):
        urllib.request.urlopen(direct, timeout=5)
    with urllib.request.urlopen(f"http://{address}:8290/status", timeout=5) as answer:
        assert answer.status == 200


def tokens(host, tmp_path, **over):
    variables = {"front_door_token_dir": str(tmp_path / "tokens"), **over}
    return testbed.run_playbook(
        host, variables, extra_inventory=door_inventory(testbed.name(host)), playbook="playbooks/front_door_token.yml"
    )


def check_the_api(host, address, bearer):
    """The fleet's API behind the door: a program with a token reads the fleet as the dashboard does;
    without one it gets 401 in JSON (never the login page); its health and description need no
    login; an instance's journal is an operator's."""
    name = testbed.name(host)
    response, data, _v = request(address, "GET", "/api/fleet", headers=bearer)
    assert response.status == 200 and response.getheader("Content-Type") == "application/json", data[:300]
    fleet = json.loads(data)
    [door_host] = fleet["hosts"]
    assert (fleet["user"], door_host["name"], door_host["reachable"]) == ("olga", name, True), fleet
    assert [i["id"] for i in door_host["instances"]] == list(range(INSTANCES))
    assert all(i["ready"] and i["release"] == "6.x" and i["holder"] is None for i in door_host["instances"])
    response, data, _v = request(address, "GET", "/api/fleet")
    assert response.status == 401 and json.loads(data)["error"].startswith("log in, or send an API token")
    assert request(address, "GET", "/api/health")[0].status == 200
    response, data, _v = request(address, "GET", "/api/openapi.json")
    assert json.loads(data)["info"]["title"] == "Isaac Sim fleet API"
    logs = f"/api/hosts/{name}/instances/1/logs?tail=5"
    response, data, _v = request(address, "GET", logs, headers=bearer)
    assert response.status == 200 and len(data.decode().splitlines()) == 5, data[:300]
    viewer = login(address, "vic", "view-secret").getheader("Set-Cookie").split(";", 1)[0].split("=", 1)[1]
    assert request(address, "GET", logs, cookie=viewer)[0].status == 403
    assert request(address, "GET", f"/api/hosts/{name}/instances/1", cookie=viewer)[0].status == 200
    # a viewer's action is refused by the API itself, whatever the page shows (it shows no buttons)
    response, data, _v = request(address, "POST", f"/api/hosts/{name}/instances/1/restart", cookie=viewer)
    assert response.status == 403 and json.loads(data)["error"] == "operators only", data[:300]


def api_call(address, method, path, token, body=None, timeout=30):
    """(status, answer) of the fleet API with a token, a JSON body or none."""
    context = ssl.create_default_context(cafile=str(ca_dir() / "ca.crt"))
    conn = http.client.HTTPSConnection(address, 443, context=context, timeout=timeout)
    headers = {"Authorization": f"Bearer {token}", "Content-Type": "application/json"}
    conn.request(method, path, body=json.dumps(body) if body is not None else None, headers=headers)
    response = conn.getresponse()
    data = response.read()
    conn.close()
    try:
        return response.status, json.loads(data)
    except ValueError:
        return response.status, data


def acted(address, token, path, body=None) -> dict:
    """An action through the API that is taken (202), followed through the door to its end: its events."""
    code, answer = api_call(address, "POST", path, token, body)
    assert code == 202, (code, answer)
    code, stream = api_call(address, "GET", answer["events"], token, timeout=120)
    events = [json.loads(line) for line in stream.decode().splitlines()]
    assert code == 200 and events[-1]["state"] == "succeeded", events
    return dict(answer, events=events)


def curl_as_a_ci_job(host, address, token, api) -> dict:
    """The guide's curl lines, as a CI job runs them (on the test host, with the door's CA and the token
    in files): the fleet listed, instance 2 restarted and its events followed to the end. The action."""
    sh(host, f"umask 077 && printf '%s' {shlex.quote(token)} > /root/olga-ops.token")
    sh(host, f"printf '%s' {shlex.quote((ca_dir() / 'ca.crt').read_text())} > /root/door-ca.crt")
    curl = 'curl -sS -f --cacert /root/door-ca.crt -H "Authorization: Bearer $(cat /root/olga-ops.token)"'
    listed = json.loads(sh(host, f"{curl} https://{address}/api/fleet").stdout)
    assert [h["name"] for h in listed["hosts"]] == [testbed.name(host)], listed
    taken = json.loads(sh(host, f"{curl} -X POST https://{address}{api}/instances/2/restart").stdout)
    events = [
        json.loads(line) for line in sh(host, f"{curl} -N 'https://{address}{taken['events']}'").stdout.splitlines()
    ]
    assert events[-1]["state"] == "succeeded", events
    return dict(taken, events=events)


AGENT = "isaac-sim-agent.service"


def check_actions(host, address, tmp):
    """Actions through the fleet's API, run on the host by its agent through the one lifecycle: a token
    restarts an instance and follows its progress; the instance's journal says who; a deploy's hold
    refuses an action naming it; below N-1 asks for a confirmation; the API killed in the middle of a
    restart does not stop it; the agent answers the door's certificate alone, from the door alone."""
    name, api = testbed.name(host), f"/api/hosts/{testbed.name(host)}"
    ok(tokens(host, tmp, front_door_token_state="present", front_door_token_user="olga",
              front_door_token_name="ops", front_door_token_scopes=["read", "use", "act", "operate"]))  # fmt: skip
    [file] = (tmp / "tokens").glob("*-olga-ops.token")
    token = file.read_text().strip()

    done = curl_as_a_ci_job(host, address, token, api)
    texts = [e["text"] for e in done["events"]]
    assert texts[0] == "accepted: restart isaac-sim-2 by olga (token ops)" and any(
        "restart of isaac-sim-2 done" in t for t in texts
    )
    assert testbed.instance_ready(host, 2)
    in_journal(host, "isaac-sim@2.service", f"action {done['id']} restart isaac-sim-2 by olga (token ops): succeeded")
    in_journal(host, UNITS[3], f"action user=olga token=ops restart {name}/2 from=")

    # a deploy holds the host (its lock as a playbook run writes it): refused, naming it, nothing done
    now = time.time()
    holder = {"id": "ctl:1:2", "user": "bob", "controller": "ctl", "pid": 1, "started": "2", "play": "Deploy",
              "since": now, "renewed": now}  # fmt: skip
    sh(host, f"echo '{json.dumps(holder)}' > /run/lock/isaac-sim.json")
    try:
        code, answer = api_call(address, "POST", f"{api}/instances/2/restart", token)
        assert code == 409 and "bob on ctl (ansible-playbook pid 1, play 'Deploy')" in answer["error"], answer
    finally:
        sh(host, "rm -f /run/lock/isaac-sim.json")

    # one instance stopped: a restart of another would take the host below N-1, so it asks first
    acted(address, token, f"{api}/instances/3/stop")
    try:
        code, answer = api_call(address, "POST", f"{api}/instances/2/restart", token)
        assert code == 412 and answer["needs_confirm"] and f"below N-1 = {INSTANCES - 1}" in answer["error"], answer
        acted(address, token, f"{api}/instances/2/restart", {"confirm": True})
        acted(address, token, f"{api}/instances/3/start")
    finally:
        sh(host, "systemctl start isaac-sim@3.service", check=False)
    testbed.all_ready(host)

    # the API killed in the middle of a restart: the host finishes it, and the API, back, says how it went
    code, answer = api_call(address, "POST", f"{api}/instances/1/restart", token)
    assert code == 202, answer
    sh(host, f"systemctl kill -s KILL {UNITS[3]}")

    def outcome():
        code, said = api_call(address, "GET", answer["url"], token)
        return code == 200 and said["state"]  # nginx's 502 while the API is away

    wait_for(lambda: outcome() == "succeeded", timeout=90, what="the restart's outcome from the API, back")
    assert testbed.instance_ready(host, 1)

    # drained: the host says so, takes no new claim (the runner's own test covers the refusal), undrained again
    code, answer = api_call(address, "POST", f"{api}/drain", token)
    assert code == 200 and answer["state"] == "succeeded", answer

    def drained():  # the API reads a host's status at most every 2 s
        return (api_call(address, "GET", api, token)[1].get("drained") or {}).get("by")

    wait_for(lambda: drained() == "olga (token ops)", timeout=15, what="the host's status to say it is drained")
    assert api_call(address, "POST", f"{api}/undrain", token)[0] == 200
    wait_for(lambda: drained() is None, timeout=15, what="the host's status to say it is not drained")

    check_a_session(host, address, token)

    # the channel: the door's certificate from the door's address; from this machine, not the door, nothing
    check_the_action_channel(address, name, tmp)
    testbed.assert_sandboxed(host, AGENT)


def check_a_session(host, address, token):
    """A simulator from the pool: the API claims a ready instance through the host's agent, the host's
    own marker names the session, an action on it is refused, a restart of the API keeps it; ended, the
    instance is restarted and only then free."""
    name = testbed.name(host)
    code, first = api_call(address, "POST", "/api/sessions", token, {})
    assert code == 201 and first["host"] == name and first["state"] == "active", first
    n, holder = first["instance"], first["holder"]
    assert api_call(address, "POST", "/api/sessions", token, {})[0] == 409  # one each
    code, refused = api_call(address, "POST", f"/api/hosts/{name}/instances/{n}/restart", token)
    assert code == 409 and f"held by {holder}" in refused["error"], refused
    wait_for(
        lambda: api_call(address, "GET", f"/api/hosts/{name}/instances/{n}", token)[1]["holder"]
        == {"kind": "session", "id": first["id"]},
        timeout=15,
        what="the fleet's listing to name the session as the instance's holder",
    )
    started = journal(host, f"isaac-sim@{n}.service").count("Started")
    sh(host, f"systemctl restart {UNITS[3]}")
    wait_for(lambda: api_call(address, "GET", first["url"], token)[0] == 200, timeout=30, what="the API back")
    assert api_call(address, "GET", first["url"], token)[1]["state"] == "active"
    code, ended = api_call(address, "DELETE", first["url"], token)
    assert code == 200 and ended["state"] == "ending" and ended["why"] == "ended by its holder", ended
    wait_for(
        lambda: api_call(address, "GET", first["url"], token)[1]["state"] == "ended",
        timeout=120,
        what="the session's instance to be reset and given back",
    )
    assert testbed.instance_ready(host, n)
    assert journal(host, f"isaac-sim@{n}.service").count("Started") > started
    in_journal(host, UNITS[3], f"session {first['id']} of user=olga started on {name}/{n}")
    in_journal(host, UNITS[3], f"session {first['id']} of user=olga ended (ended by its holder)")

    # an operator's rollout that ends sessions: the holder is warned in the session first, then its claim ends
    # on the host and the instance rolls; the door says why it ended
    code, second = api_call(address, "POST", "/api/sessions", token, {})
    assert code == 201, second
    m, rolled = second["instance"], {}
    settings = {
        "isaac_sim_rollout_end_sessions": True,
        "isaac_sim_rollout_end_sessions_warning": 12,
        "isaac_sim_instances_selected": [m],
        "isaac_sim_rollout_soak": 0,
    }
    before = testbed.container_id(host, f"isaac-sim-{m}")
    roll = threading.Thread(
        target=lambda: rolled.update(out=testbed.run_playbook(host, settings, playbook="playbooks/rolling_restart.yml"))
    )
    roll.start()
    try:
        wait_for(
            lambda: (api_call(address, "GET", second["url"], token)[1].get("warning") or "").startswith(
                "A rollout by an operator restarts this simulator at "
            ),
            timeout=90,
            what="the rollout's warning in the session",
        )
    finally:
        roll.join(timeout=300)
    said = " ".join((rolled["out"].stdout + rolled["out"].stderr).split())
    assert rolled["out"].returncode == 0, said[-3000:]
    assert f"sessions ended for this rollout: {name}: isaac-sim-{m} ({second['holder']})" in said, said[-3000:]
    assert testbed.container_id(host, f"isaac-sim-{m}") not in ("", before)
    wait_for(
        lambda: api_call(address, "GET", second["url"], token)[1]["state"] == "ended",
        timeout=45,
        what="the door to see the session's claim gone",
    )
    assert api_call(address, "GET", second["url"], token)[1]["why"] == "ended for a rollout by an operator"


def check_sessions_and_tokens(host, address, status_path, operator, tmp):
    """Sessions live on the front door: a restart of the login service keeps them, a logout ends the
    cookie's session for good (the cookie kept and sent again opens nothing). A program's token acts
    as its user within its scopes, is written down by name, and opens nothing once revoked."""
    sh(host, f"systemctl restart {UNITS[1]}")
    wait_for(lambda: request(address, "GET", status_path, cookie=operator)[0].status == 200, timeout=20)
    ended = login(address, "olga", "op-secret").getheader("Set-Cookie").split(";", 1)[0].split("=", 1)[1]
    assert request(address, "GET", status_path, cookie=ended)[0].status == 200
    response, _d, _v = request(address, "GET", "/logout", cookie=ended)
    assert response.status == 303 and "Max-Age=0" in response.getheader("Set-Cookie")
    assert request(address, "GET", status_path, cookie=ended)[0].status == 302
    assert request(address, "GET", "/session", cookie=ended)[0].status == 401
    assert request(address, "GET", "/api/fleet", cookie=ended)[0].status == 401
    in_journal(host, UNITS[1], "logout user=olga from=")
    # the operator's other session goes on
    assert request(address, "GET", status_path, cookie=operator)[0].status == 200

    made = ok(tokens(host, tmp, front_door_token_state="present", front_door_token_user="olga",
                     front_door_token_name="ci", front_door_token_scopes=["read"]))  # fmt: skip
    [file] = (tmp / "tokens").glob("*-olga-ci.token")
    token = file.read_text().strip()
    assert oct(file.stat().st_mode & 0o777) == "0o600" and token not in made.stdout
    bearer = {"Authorization": f"Bearer {token}"}
    response, data, _v = request(address, "GET", status_path, headers=bearer)
    assert response.status == 200 and json.loads(data)["host"], data[:300]
    in_journal(host, UNITS[0], f'user=olga token=ci "GET {status_path}')
    # a program gets 401, never the login page; a bad token is no token
    assert request(address, "GET", status_path, headers={"Authorization": "Bearer isf_x"})[0].status == 401
    check_the_api(host, address, bearer)
    listed = ok(tokens(host, tmp))
    assert "olga/ci (" in listed.stdout and " read active until " in listed.stdout, listed.stdout[-2000:]
    # an instance's journal followed through the door with the token, until the token is revoked
    name = testbed.name(host)
    context = ssl.create_default_context(cafile=str(ca_dir() / "ca.crt"))
    # (the journal's last line now: among the last 20 the stream starts with, however long the journal is)
    last = sh(host, "journalctl -u isaac-sim@1.service -o short-iso --no-pager -q -n 1").stdout.strip().encode()
    with context.wrap_socket(socket.create_connection((address, 443), timeout=30), server_hostname=address) as tls:
        # HTTP/1.0: nginx sends the stream as it is, not in chunks
        tls.sendall(
            f"GET /api/hosts/{name}/instances/1/logs?follow=1 HTTP/1.0\r\nHost: {address}\r\n"
            f"Authorization: Bearer {token}\r\n\r\n".encode()
        )
        got = b""
        while last not in got.partition(b"\r\n\r\n")[2]:
            got += tls.recv(65536)
        assert got.startswith(b"HTTP/1.1 200 "), got[:300]
        ok(tokens(host, tmp, front_door_token_state="absent", front_door_token_user="olga", front_door_token_name="ci"))
        revoked = time.monotonic()
        with contextlib.suppress(ssl.SSLError):  # nginx may end TLS without its close_notify
            while chunk := tls.recv(65536):
                got += chunk
        # the API asks again every 3 s, and reads for 1 s at most between: within 5 s of the revocation
        # (measured here from the end of the playbook run that revoked it, so a little less)
        ended = time.monotonic() - revoked
        print(f"a followed journal ended {ended:.1f} s after its token's revocation")
        assert ended < 5 and b"[the session or token ended" in got, (ended, got[-500:])
    in_journal(host, UNITS[3], f"follow user=olga token=ci path='/api/hosts/{name}/instances/1/logs'")
    assert request(address, "GET", status_path, headers=bearer)[0].status == 401
    in_journal(host, UNITS[1], f"refused user=- path='{status_path}' from=")


def test_the_front_door_lets_in_logged_in_users_only_over_tls_and_goes_away_cleanly(host, tmp_path):
    address = testbed.host_ip(host)
    first = ok(run(host, front_door_server_name=address))
    try:
        again = ok(run(host, front_door_server_name=address))
        assert testbed.changed_count(again, host) == 0, again.stdout[-3000:]

        # plain HTTP only redirects
        response, _d, _v = request(address, "GET", "/hosts/x/status", tls=False)
        assert response.status == 301 and response.getheader("Location") == f"https://{address}/hosts/x/status"

        # without a session: to the login page, over TLS 1.2+ with the CA's certificate, HSTS on
        status_path = f"/hosts/{testbed.name(host)}/status"
        response, _d, version = request(address, "GET", status_path)
        assert response.status == 302 and response.getheader("Location") == f"/login?next={status_path}"
        assert version in ("TLSv1.2", "TLSv1.3")
        assert response.getheader("Strict-Transport-Security") == "max-age=31536000"
        in_journal(host, UNITS[1], "refused user=- path='" + status_path)
        # a page's own request (fetch) gets 401, as it cannot follow a login page
        assert request(address, "GET", status_path, headers={"Sec-Fetch-Dest": "empty"})[0].status == 401

        # a wrong password is refused and written down with the user's name
        assert login(address, "olga", "guess").status == 401
        in_journal(host, UNITS[1], "login refused user=olga")

        # the operator logs in: a Secure, HttpOnly, SameSite cookie; the status comes through
        response = login(address, "olga", "op-secret")
        assert response.status == 303
        cookie = response.getheader("Set-Cookie")
        assert {"Secure", "HttpOnly", "SameSite=Lax"} <= {p.strip() for p in cookie.split(";")}
        operator = cookie.split(";", 1)[0].split("=", 1)[1]
        response, data, _v = request(address, "GET", status_path, cookie=operator)
        assert response.status == 200, data[:500]
        assert json.loads(data)["host"]
        # a forged cookie is no session
        assert request(address, "GET", status_path, cookie=operator[:-2] + "xx")[0].status == 302
        check_sessions_and_tokens(host, address, status_path, operator, tmp_path)
        check_actions(host, address, tmp_path)

        # a viewer opens the status but not an operator's path; the operator passes it
        viewer = login(address, "vic", "view-secret").getheader("Set-Cookie").split(";", 1)[0].split("=", 1)[1]
        assert request(address, "GET", status_path, cookie=viewer)[0].status == 200
        # however the path is written: nginx's own match of it decides what it needs
        for path in (
            "/operator/logs",
            "/%6Fperator/logs",
            "//operator/logs",
            "/./operator/logs",
            "/a/../operator/logs",
        ):
            assert request(address, "GET", path, cookie=viewer)[0].status == 403, path
            assert request(address, "GET", path, cookie=operator)[0].status == 404, path
        in_journal(host, UNITS[1], "refused user=vic path='/%6Fperator/logs'")
        check_the_logs(host, address, viewer, operator)

        # the dashboard, served behind the login, in a browser that trusts the collection's CA
        dashboard_in_chromium(host, address, tmp_path)

        # guessing is rate-limited per client address (30/min, a burst of 5)
        codes = [login(address, "olga", f"guess-{i}").status for i in range(12)]
        assert 429 in codes and codes[0] == 401, codes
        # and each throttled try is logged with the user name it tried
        in_journal(host, UNITS[1], "login throttled user=olga from=")

        for unit in UNITS:
            testbed.assert_sandboxed(host, unit)
        # the distribution's own nginx and coturn, installed by the role, do not run
        for own in ("nginx.service", "coturn.service"):
            assert sh(host, f"systemctl is-active {own}", check=False).stdout.strip() != "active", own
        # vic holds a simulator, with a file of the session's own in it, when the door is removed (asked before
        # the door asks for people's client certificates below)
        code, held = as_person(address, "POST", "/api/sessions", viewer, {})
        assert code == 201, held
        kept_before = testbed.container_id(host, f"isaac-sim-{held['instance']}")
        sh(host, f"docker exec isaac-sim-{held['instance']} sh -c 'echo last > {DOCUMENTS}/last-session.txt'")
        check_client_certificates(host, address, tmp_path / "people")
        # the sessions' figures for node_exporter, from the file (a restart of the API keeps their sums)
        figures = sh(host, f"cat {SESSIONS_PROM}").stdout
        assert "isaac_sim_door_sessions_active " in figures and "isaac_sim_door_session_wait_seconds_count " in figures
    finally:
        gone = ok(run(host, front_door_server_name=address, front_door_state="absent"))
    assert "changed" in first.stdout
    for unit in UNITS:
        assert sh(host, f"systemctl cat {unit}", check=False).rc != 0
    assert sh(host, "test -e /etc/isaac-sim/front-door", check=False).rc != 0
    # the sessions' figures go with it; what people saved stays
    assert sh(host, f"test -e {SESSIONS_PROM}", check=False).rc != 0
    assert f"{hashlib.sha256(b'vic').hexdigest()}.tar" in sh(host, f"ls {FILES_DIR}").stdout
    assert sh(host, "ss -ltn 'sport = :443 or sport = :5349'").stdout.count("LISTEN") == 0
    # the removal ended vic's session first: the instance given back (a fresh container, ready, held by
    # nobody) and the session's file kept with vic's others on the door
    said = " ".join(gone.stdout.split())
    assert "End the sessions, waiting for the hosts to give their instances back" in said, said[-3000:]
    assert ".lent" not in sh(host, "ls /run/isaac-sim").stdout
    assert testbed.container_id(host, f"isaac-sim-{held['instance']}") not in ("", kept_before)
    assert testbed.instance_ready(host, held["instance"])
    tar = f"{FILES_DIR}/{hashlib.sha256(b'vic').hexdigest()}.tar"
    assert "last-session.txt" in sh(host, f"tar -tf {tar}").stdout
    ending = sh(host, "journalctl -t isaac-sim-front-door-api --no-pager -o cat").stdout
    where = f"{testbed.name(host)}/{held['instance']}"
    assert f"session {held['id']} of user=vic on {where} ends: the front door was removed" in ending, ending[-2000:]
    assert testbed.changed_count(ok(run(host, front_door_state="absent")), host) == 0, gone.stdout[-2000:]
