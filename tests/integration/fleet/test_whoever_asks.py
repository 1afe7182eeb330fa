"""Simulators for whoever asks, from one pool across the fleet: the front door on the mirror's host (no
instance there) hands the hosts' instances to nine people, shares them with a test suite, keeps every
claim and place through a reboot of its own host, frees the claims of a host that stops answering, and
ends sessions left idle or at their maximum duration, each with its warning first.

Runs last of the fleet's modules (file order), after test_viewers_through_the_gateway.py, whose deploy
gave the first host a web viewer beside each instance behind the door: a session there has a stream
the door relays (so it can end idle, and its viewer is the holder's alone). Its fixture deploys the
first two hosts again with the action agent the door reaches them through (the first with that
module's settings kept); the third runs none (by then it runs two instances: test_unwanted_traffic.py
scaled it down), so the door hands out the first two hosts' eight instances alone.
"""

from __future__ import annotations

import json
import time
from concurrent.futures import ThreadPoolExecutor

import pytest
import testbed
import yaml
from browser import chromium, console_errors
from fleethosts import INSTANCES, hosts, ip, playbook, sh, squash
from frontdoor import as_person, ca_dir, check_the_action_channel, log_in, request, session, settings
from selenium.webdriver.support.ui import Select
from test_stream_addresses import viewer_image
from test_suite import FIXTURES, image
from test_viewers_through_the_gateway import DOOR, DOOR_VIEWER, front_door, ok

# the stand-in's Documents (6.x: NVIDIA's mount for the isaac-sim user) and a file vic saves there
DOCUMENTS, MARKER = "/isaac-sim/Documents", "vic-marker.txt"
PEOPLE = ("ana", "ben", "cy", "dee", "eve", "fay", "gus")  # with vic, eight; val is the ninth
# the door's rules for these tests: a host that does not answer for 30 s loses its sessions; no idle end
# and a long maximum until the last test sets its own; logins as fast as nine people make them
RULES = {
    "front_door_sim_host_gone_seconds": 30,
    "front_door_sim_idle_minutes": 0,
    "front_door_login_rate": "600r/m",
}


def door_settings(**over) -> dict:
    return settings(front_door_server_name=ip(DOOR), **dict(RULES, **over))


@pytest.fixture(scope="module")
def door():
    """The door's address and an operator's cookie: the first two hosts run the action agent for the door
    (its address alone, the scenario's CA), the door is deployed with the sessions' rules, and those hosts'
    instances are ready and held by nobody."""
    first, second, _third = hosts()
    address = ip(DOOR)
    agent = {
        "isaac_sim_agent_enabled": True,
        "isaac_sim_agent_allow": [f"{address}/32"],
        "isaac_sim_agent_ca_dir": str(ca_dir()),
    }
    # the first host as test_viewers_through_the_gateway.py deployed it, with the agent beside
    gateway = {
        "isaac_sim_web_viewer_image": viewer_image(first),
        "isaac_sim_allowed_networks_by_port": {"signal": [f"{address}/32"], "web_viewer": [f"{address}/32"]},
        "isaac_sim_status_server_logs_allow": [f"{address}/32"],
    }
    with ThreadPoolExecutor(2) as pool:
        # the second host's last instance headless: the fleet offers two profiles, which the page lets a person pick
        headless = dict(agent, isaac_sim_instance_profiles={3: "headless"})
        deploys = [pool.submit(playbook, "deploy.yml", dict(gateway, **agent), first),
                   pool.submit(playbook, "deploy.yml", headless, second)]  # fmt: skip
        for deployed in deploys:
            ok(deployed.result())
    for h in (first, second):
        testbed.wait_for(lambda h=h: ready_and_free(h), timeout=240, what=f"{h} ready")
    ok(front_door(door_settings()))
    olga = session(address, "olga", "op-secret")
    yield address, olga
    for h in (first, second):
        as_person(address, "POST", f"/api/hosts/{h}/undrain", olga)


def ready_and_free(host: str, n: int = INSTANCES) -> bool:
    out = sh(host, "ls /run/isaac-sim; systemctl is-active isaac-sim@0 isaac-sim@1 isaac-sim@2 isaac-sim@3 || true")
    return out.count("active\n") >= n and out.count(".ready") >= n and ".lent" not in out


def holders(host: str) -> dict:
    """{instance: holder} of the host's claims, as its own markers say (a run's or a session's)."""
    out = sh(host, "for d in /run/isaac-sim/instance-*.lent; do [ -d $d ] && echo $d $(head -1 $d/run); done; true")
    return {int(d.rsplit("-", 1)[1].split(".")[0]): who for d, who in (line.split() for line in out.splitlines())}


def drain(address: str, olga: str, host: str, undo: bool = False) -> None:
    code, answer = as_person(address, "POST", f"/api/hosts/{host}/{'undrain' if undo else 'drain'}", olga)
    assert code == 200 and answer["state"] == "succeeded", answer

    def said():  # the API reads a host's status at most every 2 s
        return as_person(address, "GET", f"/api/hosts/{host}", olga)[1].get("drained")

    testbed.wait_for(lambda: bool(said()) != undo, timeout=15, what=f"{host} {'undrained' if undo else 'drained'}")


def logged_in(address: str, *names: str) -> dict:
    """{name: session cookie}, one login each, spaced as the rules let one address log in (10 a second)."""
    cookies = {}
    for name in names:
        time.sleep(0.2)
        cookies[name] = session(address, name, "view-secret")
    return cookies


def ask(address: str, cookie: str) -> tuple[int, dict]:
    return as_person(address, "POST", "/api/sessions", cookie, {})


def look(address: str, cookie: str, sid: str) -> dict:
    """A session or place as its holder sees it (a look keeps a place in the queue)."""
    code, answer = as_person(address, "GET", f"/api/sessions/{sid}", cookie)
    assert code == 200, answer
    return answer


def end_everything(address: str, olga: str, *free_hosts: str) -> None:
    """Every session and place ended by the operator, then each host's instances reset and free."""
    _code, everything = as_person(address, "GET", "/api/sessions", olga)
    for s in everything["sessions"] + everything["queue"]:
        if s["state"] in ("active", "queued"):
            assert as_person(address, "DELETE", s["url"], olga)[0] == 200, s
    testbed.wait_for(
        lambda: not as_person(address, "GET", "/api/sessions", olga)[1]["sessions"],
        timeout=180,
        what="every session ended and its instance reset",
    )
    for h in free_hosts:
        testbed.wait_for(lambda h=h: ready_and_free(h), timeout=180, what=f"{h}'s instances free")


def test_a_host_s_action_channel_takes_the_door_alone(door, tmp_path):
    """The first host's agent: from the door's own address, the door's certificate gets an answer, and
    neither no certificate nor one of another CA in the door's name does. From the third host, a test
    host that is not the door, nothing reaches the port, whatever certificate it shows."""
    first, _second, third = hosts()
    check_the_action_channel(ip(first), DOOR, tmp_path, elsewhere=third)


def test_a_test_suite_and_sessions_share_one_pool(door, tmp_path):
    """One host open to claims: two people hold two instances, a suite's run borrows one of the other
    two (never a held one), the next person gets the last, and the one after waits for the suite's,
    which they get once the run gave it back (restarted)."""
    address, olga = door
    first, second, _third = hosts()
    drain(address, olga, second)
    cookies = logged_in(address, "ana", "ben", "cy", "dee")
    held = {name: ask(address, cookies[name]) for name in ("ana", "ben")}
    assert all(code == 201 and s["host"] == first for code, s in held.values()), held
    mine = {s["instance"] for _c, s in held.values()}
    assert len(mine) == 2

    spec = {
        "environment": {"IMAGE": image(first), "HOLD_S": "20"},
        "timeout": 300,
        "experiences": [{"file": str(FIXTURES / "sim.yml")}],
    }
    out = tmp_path
    (out / "suite.yml").write_text(yaml.safe_dump(spec))
    extra = {"test_suite_file": str(out / "suite.yml"), "test_suite_dir": str(out / "runs"), "test_suite_gpus": []}
    with ThreadPoolExecutor(1) as pool:
        suite = pool.submit(playbook, "test_suite.yml", extra, first)

        def borrowed():
            return {n: who for n, who in holders(first).items() if not who.startswith("session-")}

        testbed.wait_for(lambda: borrowed() or suite.done(), timeout=180, what="the suite's run to borrow an instance")
        [(x, run)] = borrowed().items()
        assert x not in mine, (x, mine)
        code, cy = ask(address, cookies["cy"])
        assert code == 201 and cy["host"] == first and cy["instance"] not in mine | {x}, cy
        code, dee = ask(address, cookies["dee"])
        assert code == 202 and dee["place"] == 1, dee
        testbed.wait_for(
            lambda: look(address, cookies["dee"], dee["id"])["state"] == "active",
            timeout=240,
            what="dee to get the instance the suite gave back",
        )
        done = suite.result()
    assert done.returncode == 0, squash(done.stdout + done.stderr)[-3000:]
    [result] = json.loads((out / "runs" / "suite.json").read_text())["results"]
    assert result["instance"] == x and result["run"] in run and result["verdict"]["result"] == "passed", result
    dee = look(address, cookies["dee"], dee["id"])
    assert (dee["host"], dee["instance"]) == (first, x), dee
    end_everything(address, olga, first)
    drain(address, olga, second, undo=True)


def test_nine_people_on_two_hosts_in_chromium_and_a_reboot_of_the_door(door):
    """Eight people ask at once and get the two hosts' eight instances; val, the ninth, waits in Chromium
    with their place shown, and gets the one vic ends, already reset: vic's saved file is gone from it,
    and back in vic's next session, on the other host. Nobody opens another's viewer. A reboot of the
    door's host keeps every session, claim and place; a person's login too."""
    address, olga = door
    first, second, _third = hosts()
    cookies = logged_in(address, "vic", "val", *PEOPLE)
    askers = ("vic", *PEOPLE)
    with ThreadPoolExecutor(len(askers)) as pool:
        got = dict(zip(askers, pool.map(lambda name: ask(address, cookies[name]), askers)))
    assert [code for code, _s in got.values()] == [201] * 8, got
    sessions = {name: s for name, (_c, s) in got.items()}
    places = {(s["host"], s["instance"]) for s in sessions.values()}
    assert len(places) == 8 and {h for h, _n in places} == {first, second}, places
    assert sorted(h for h, _n in places).count(first) == INSTANCES, places
    # each claim is the host's own marker, naming the session
    for h in (first, second):
        assert sorted(holders(h).values()) == sorted(s["holder"] for s in sessions.values() if s["host"] == h)

    # a viewer of the first host is its holder's alone (and an operator's): anyone else gets 403 at the door
    owner = next(name for name in PEOPLE if sessions[name]["host"] == first)
    port = DOOR_VIEWER + sessions[owner]["instance"]
    other = next(name for name in PEOPLE if name != owner)
    for who, status in ((owner, 200), ("olga", 200), (other, 403), ("val", 403)):
        cookie = olga if who == "olga" else cookies[who]
        assert request(address, "GET", "/", cookie=cookie, port=port)[0].status == status, who
    upgrade = {"Upgrade": "websocket", "Connection": "Upgrade", "Sec-WebSocket-Version": "13",
               "Sec-WebSocket-Key": "dGhlIHNhbXBsZSBub25jZQ==", "Origin": f"https://{address}:{port}"}  # fmt: skip
    assert request(address, "GET", "/", cookie=cookies[other], port=port, headers=upgrade)[0].status == 403
    # a cookie logged out opens neither the page nor its signalling, though its person holds the instance
    spare = logged_in(address, owner)[owner]
    assert request(address, "GET", "/", cookie=spare, port=port)[0].status == 200
    assert request(address, "GET", "/logout", cookie=spare)[0].status == 303
    for headers in (None, upgrade):
        assert request(address, "GET", "/", cookie=spare, port=port, headers=headers)[0].status in (302, 401)

    vic = sessions["vic"]
    gave = next(name for name in PEOPLE if sessions[name]["host"] != vic["host"])
    with chromium(trust_ca=ca_dir() / "ca.crt") as vics, chromium(trust_ca=ca_dir() / "ca.crt") as vals:
        pages = {"vic": vics, "val": vals}
        for name, driver in pages.items():
            simulator_page(driver, address, name)
        assert text(vics, "state") == f"Your simulator: {vic['host']}, instance {vic['instance']}."
        vals.find_element("id", "ask").click()
        testbed.wait_for(lambda: data(vals, "state") == "queued", timeout=15, what="val in the queue")
        assert text(vals, "state").startswith("You are number 1 of 1 in the queue"), text(vals, "state")

        at, n = vic["host"], vic["instance"]
        before = sh(at, f"docker inspect -f '{{{{.Id}}}}' isaac-sim-{n}").strip()
        sh(at, f"docker exec isaac-sim-{n} sh -c 'mkdir -p {DOCUMENTS}/work && echo vic > {DOCUMENTS}/work/{MARKER}'")
        vics.find_element("id", "end").click()
        testbed.wait_for(lambda: data(vics, "state") == "ended", timeout=120, what="vic's session to end")
        assert text(vics, "state") == "Your session ended (ended by its holder)."
        testbed.wait_for(lambda: data(vals, "state") == "active", timeout=120, what="val's simulator")
        assert text(vals, "state") == f"Your simulator: {at}, instance {n}."
        # reset before val got it: a fresh container, without vic's file
        assert sh(at, f"docker inspect -f '{{{{.Id}}}}' isaac-sim-{n}").strip() != before
        assert sh(at, f"docker exec isaac-sim-{n} ls -A {DOCUMENTS}").strip() == ""

        # one on the other host ends; vic asks again and gets that one, with vic's file put back there
        assert as_person(address, "DELETE", sessions[gave]["url"], cookies[gave])[0] == 200
        testbed.wait_for(
            lambda: look(address, cookies[gave], sessions[gave]["id"])["state"] == "ended",
            timeout=120,
            what=f"{gave}'s session to end",
        )
        vics.find_element("id", "ask").click()
        testbed.wait_for(lambda: data(vics, "state") == "active", timeout=60, what="vic's next simulator")
        again = (sessions[gave]["host"], sessions[gave]["instance"])
        assert text(vics, "state") == f"Your simulator: {again[0]}, instance {again[1]}."
        assert again[0] != at
        testbed.wait_for(
            lambda: "vic" in sh(again[0], f"docker exec isaac-sim-{again[1]} cat {DOCUMENTS}/work/{MARKER} || true"),
            timeout=60,
            what="vic's file in vic's next simulator, on the other host",
        )
        code, waiting = ask(address, cookies[gave])
        assert code == 202 and waiting["place"] == 1, waiting

        door_reboot_keeps_everything(address, olga, cookies[gave], waiting["id"], pages)
        for name, driver in pages.items():
            testbed.wait_for(lambda d=driver: data(d, "state") == "active", timeout=30, what=f"{name}'s page again")
        assert text(vals, "state") == f"Your simulator: {at}, instance {n}."
    end_everything(address, olga, first, second)


def door_reboot_keeps_everything(address: str, olga: str, waiter: str, place: str, pages: dict) -> None:
    """The door's host rebooted (a power cut: its container restarted) while eight hold instances and one
    waits: every session, claim and place is as it was, and the operator's login still holds."""
    first, second, _third = hosts()

    def held_and_queued():
        _code, everything = as_person(address, "GET", "/api/sessions", olga)
        held = sorted((s["user"], s["host"], s["instance"], s["state"]) for s in everything["sessions"])
        return held, [q["user"] for q in everything["queue"]]

    before, claims = held_and_queued(), {h: holders(h) for h in (first, second)}
    assert len(before[0]) == 8 and len(before[1]) == 1, before
    look(address, waiter, place)
    testbed.client().containers.get(DOOR).restart(timeout=0)
    testbed.wait_for(
        lambda: sh(DOOR, "systemctl is-system-running --wait || true").strip() in ("running", "degraded"),
        timeout=120,
        what="the door's host to boot",
    )
    assert ip(DOOR) == address, "the door's host came back at another address (Docker's bridge gave it away)"
    testbed.wait_for(
        lambda: request(address, "GET", "/api/health")[0].status == 200, timeout=60, what="the door to answer"
    )
    assert held_and_queued() == before
    assert look(address, waiter, place)["place"] == 1
    assert {h: holders(h) for h in (first, second)} == claims
    # after the door's next look at what each host holds for it (every 10 s): still all of them
    time.sleep(12)
    assert held_and_queued() == before


def test_a_host_that_stops_answering_frees_its_claims_and_tells_their_holders(door):
    """The second host frozen (docker pause: nothing on it answers, as a host powered off or cut off)
    while two people hold its instances: after the door's 30 s their sessions are over and each holder's
    view says why; nobody is given that host's instances meanwhile. Back, the host gives each claim back
    (the instance reset) and the next person gets one."""
    address, olga = door
    first, second, _third = hosts()
    drain(address, olga, first)
    cookies = logged_in(address, "ana", "ben", "cy")
    got = {name: ask(address, cookies[name]) for name in ("ana", "ben")}
    assert all(code == 201 and s["host"] == second for code, s in got.values()), got
    host = testbed.client().containers.get(second)
    host.pause()
    paused = time.monotonic()
    try:
        # the fleet's listing meanwhile: the frozen host unreachable, the other served (printed: how long it took)
        time.sleep(2.5)  # past the API's reuse of its last read (2 s)
        began = time.monotonic()
        code, listing = as_person(address, "GET", "/api/fleet", olga)
        print(f"the fleet listing with {second} frozen answered in {time.monotonic() - began:.2f} s")
        reach = {h["name"]: h["reachable"] for h in listing["hosts"]}
        assert code == 200 and reach[second] is False and reach[first] is True, reach
        testbed.wait_for(
            lambda: all(look(address, cookies[n], s["id"])["state"] != "active" for n, (_c, s) in got.items()),
            timeout=120,
            what=f"the sessions on {second} to be over",
        )
        over = time.monotonic() - paused
        # the door's last answer from the host came at most a read (2 s) before the pause
        assert 27 <= over <= 75, over
        for name, (_c, s) in got.items():
            why = look(address, cookies[name], s["id"])["why"]
            assert why.startswith(f"{second} did not answer for ") and why.endswith("; the session is over"), why
        code, waiting = ask(address, cookies["cy"])
        assert code == 202 and waiting["place"] == 1, waiting
    finally:
        host.unpause()
    # (cy, first in the queue, may get a free one of them before these are given back: the door offers a host's
    # instances again as soon as it answers)
    ended = {s["holder"] for _c, s in got.values()}
    testbed.wait_for(
        lambda: not ended & set(holders(second).values()), timeout=180, what=f"{second} to give their claims back"
    )
    for name, (_c, s) in got.items():
        testbed.wait_for(
            lambda n=name, s=s: look(address, cookies[n], s["id"])["state"] == "ended",
            timeout=60,
            what=f"{name}'s session ended",
        )
    testbed.wait_for(
        lambda: look(address, cookies["cy"], waiting["id"])["state"] == "active",
        timeout=120,
        what="cy to get an instance of the host back",
    )
    assert look(address, cookies["cy"], waiting["id"])["host"] == second
    end_everything(address, olga, second)
    drain(address, olga, first, undo=True)


def test_idle_and_maximum_duration_ends_come_on_time_with_their_warnings_first(door):
    """Idle 2 minutes, at most 3, warned 1 minute before: ana, on nobody's stream, is warned in her page
    after a minute and her session ends at two; val keeps a viewer on his stream, so his session does
    not end idle: he is warned at two minutes and it ends at three, its maximum."""
    address, olga = door
    first, second, _third = hosts()
    ok(front_door(door_settings(front_door_sim_idle_minutes=2, front_door_sim_max_minutes=3,
                                front_door_sim_warn_minutes=1)))  # fmt: skip
    drain(address, olga, second)
    with chromium(trust_ca=ca_dir() / "ca.crt") as anas, chromium(trust_ca=ca_dir() / "ca.crt") as vals:
        held = {}
        for name, driver in (("ana", anas), ("val", vals)):
            simulator_page(driver, address, name)
            if name == "val":
                # the fleet runs two profiles (the fixture's headless instance): the page offers them, and val
                # asks for a streaming one
                testbed.wait_for(lambda: vals.find_elements("id", "want-profile"), timeout=15, what="the choices")
                choice = Select(driver.find_element("id", "want-profile"))
                assert [o.text for o in choice.options] == ["any", "headless", "streaming"]
                assert not driver.find_elements("id", "want-release")  # one release: nothing to choose
                choice.select_by_value("streaming")
            driver.find_element("id", "ask").click()
            testbed.wait_for(lambda d=driver: data(d, "state") == "active", timeout=60, what=f"{name}'s simulator")
            cookie = logged_in(address, name)[name]
            [mine] = as_person(address, "GET", "/api/sessions", cookie)[1]["mine"]
            held[name] = (cookie, mine)
        assert held["val"][1]["wants"] == {"profile": "streaming"} and held["ana"][1]["wants"] == {}
        # the door's own times (the same clock as this machine's: the test hosts are containers here)
        started = {name: mine["started"] for name, (_c, mine) in held.items()}

        def ended(name):
            cookie, mine = held[name]
            return look(address, cookie, mine["id"])["ended"] - started[name]

        n = int(text(vals, "state").rsplit(" ", 1)[1].rstrip("."))
        assert text(vals, "state") == f"Your simulator: {first}, instance {n}."
        # val's stream, in a tab of its own: its signalling through the door, as the gateway's test opens it
        simulator = vals.current_window_handle
        vals.switch_to.new_window("tab")
        vals.get(f"https://{address}/viewers/{first}/{n}/")
        testbed.wait_for(lambda: data(vals, "configured") == "yes", timeout=15, what="val's viewer")
        vals.get(f"https://{address}:{DOOR_VIEWER + n}/?connect")
        testbed.wait_for(lambda: data(vals, "signalling") == "open", timeout=15, what="val's signalling")
        vals.switch_to.window(simulator)

        warned = testbed.wait_for(lambda: text(anas, "warning") or None, timeout=90, interval=0.5, what="ana's warning")
        assert time.time() - started["ana"] >= 59.5, warned
        assert warned.startswith("Nobody has been on this simulator's stream for 1 minute(s): it ends in 1 minute(s)")
        assert text(vals, "warning") == ""
        testbed.wait_for(lambda: data(anas, "state") == "ended", timeout=90, what="ana's idle end")
        assert text(anas, "state") == "Your session ended (nobody on its stream for 2 minutes)."
        assert 120 <= ended("ana") <= 135, ended("ana")
        assert data(vals, "state") == "active"

        warned = testbed.wait_for(lambda: text(vals, "warning") or None, timeout=60, interval=0.5, what="val's warning")
        assert time.time() - started["val"] >= 119.5, warned
        assert warned == "This session ends in 1 minute(s), at its maximum duration. Save your work where it is kept."
        testbed.wait_for(lambda: data(vals, "state") == "ended", timeout=90, what="val's end at its maximum")
        assert text(vals, "state") == "Your session ended (its maximum duration (3 minutes))."
        assert 180 <= ended("val") <= 195, ended("val")
        assert console_errors(anas) == []
    end_everything(address, olga, first)
    drain(address, olga, second, undo=True)


def simulator_page(driver, address: str, name: str) -> None:
    """The person's simulator page, after its login."""
    driver.get(f"https://{address}/simulator.html")
    testbed.wait_for(lambda: "/login?next=" in driver.current_url, timeout=15, what=f"{name}'s login")
    log_in(driver, name, "view-secret")
    testbed.wait_for(lambda: data(driver, "ready") == "yes", timeout=15, what=f"{name}'s page")


def data(driver, name: str):
    try:
        return driver.find_element("tag name", "body").get_attribute(f"data-{name}")
    except Exception:  # noqa: BLE001  (the page is being replaced: ask again)
        return None


def text(driver, element: str) -> str:
    return driver.find_element("id", element).text
