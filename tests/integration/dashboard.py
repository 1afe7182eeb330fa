"""status.yml's dashboard, written and then read the way a person does: in headless Chromium."""

import re
import time
import urllib.parse
from pathlib import Path

import testbed
from browser import chromium, console_errors

OUTPUT = testbed.ROOT / "tests" / "output"


def dashboard(host, tmp_path, extra=None):
    out = tmp_path / "report"
    run = testbed.run_playbook(host, {"fleet_report_dir": str(out), **(extra or {})}, playbook="playbooks/status.yml")
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr
    return run, out


def check_dashboard(page: Path, expected: dict, shot: Path):
    """expected: {instance id: info record}. Returns the driver's findings."""
    with chromium() as driver:
        driver.get(page.as_uri())
        time.sleep(1)  # let frames load: their failures are console errors too
        errors = console_errors(driver)
        cards = driver.find_elements("css selector", ".instance-card")
        links = [
            (c.get_attribute("data-instance"), a.get_attribute("data-kind"), a.get_attribute("href"))
            for c in cards
            for a in c.find_elements("css selector", "a.stream-link")
        ]
        addresses = [
            (c.get_attribute("data-instance"), a.get_attribute("data-kind"), a.text)
            for c in cards
            for a in c.find_elements("css selector", "code.stream-address")
        ]
        frames = [f.get_attribute("src") for f in driver.find_elements("css selector", "iframe.stream")]
        states = {c.get_attribute("data-instance"): c.get_attribute("data-state") for c in cards}
        ready_in = {
            c.get_attribute("data-instance"): c.find_element("css selector", "dd.f-ready-in").text for c in cards
        }
        summary = driver.find_element("id", "sum-instances").text
        shot.parent.mkdir(parents=True, exist_ok=True)
        driver.save_screenshot(str(shot))
        frame_text = []
        for frame in driver.find_elements("css selector", "iframe.stream"):
            driver.switch_to.frame(frame)
            frame_text.append(driver.find_element("tag name", "body").text)
            driver.switch_to.default_content()
    assert errors == [], errors
    assert len(cards) == len(expected) and summary == str(len(expected))
    assert states == {str(i): rec["state"] for i, rec in expected.items()}
    # a ready instance: how long its start took to ready, and the caches it found
    for i, rec in expected.items():
        if rec["ready"]:
            assert re.fullmatch(r"(\d+s|\d+m\d\ds) \((warm|cold) caches\)", ready_in[str(i)]), ready_in
    for instance, kind, href in links:
        url = urllib.parse.urlsplit(href)
        rec = expected[int(instance)]
        # every link points at the instance's host and at the port of its own block for that kind
        assert url.hostname == rec["public_address"], href
        port_kind = "http" if kind == "webrtc_client" else kind
        assert url.port == rec["ports"][port_kind], href
        assert href == rec["urls"][kind]
    for instance, kind, text in addresses:
        assert text == expected[int(instance)]["urls"][kind]
    return {"links": links, "addresses": addresses, "frames": frames, "frame_text": frame_text}
