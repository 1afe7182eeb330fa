"""Seeing and operating the fleet: isaac_sim_info, status.yml's dashboard, day-2 playbooks, metrics.

Runs on the molecule default host (four 6.x stand-in instances) after the
other instance tests; each test leaves every instance ready again.
"""

import json
import re
import socket
import time
import urllib.error
import urllib.request

import pytest
import testbed
from browser import chromium
from dashboard import OUTPUT, check_dashboard, dashboard
from testbed import INSTANCES, all_ready, by_name, container_id, sh, unit_show, wait_for


@pytest.fixture()
def ip(host):
    return testbed.host_ip(host)


def ok(result):
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr
    return result


@pytest.mark.core
def test_info_reports_every_instance_ready_with_its_block_and_urls(host, ip):
    all_ready(host)
    # ready by its line; healthy at the first check after it (every 5 s here)
    for i in range(INSTANCES):
        wait_for(
            lambda i=i: "(healthy)"
            in sh(host, f"docker ps --filter name=^isaac-sim-{i}$ --format '{{{{.Status}}}}'").stdout,
            timeout=30,
            what=f"isaac-sim-{i} healthy",
        )
    result = testbed.info(host)
    assert result["changed"] is False and result["deployed"] is True and result["errors"] == []
    assert result["summary"] == {"configured": 4, "running": 4, "ready": 4, "failed": 0, "stopped": 0, "stray": 0}
    digest = sh(host, "docker image inspect -f '{{index .RepoDigests 0}}' " + by_name(result)["isaac-sim-0"]["image"])
    for i in range(INSTANCES):
        inst = by_name(result)[f"isaac-sim-{i}"]
        assert inst["id"] == i and inst["configured"] and not inst["stray"]
        assert inst["state"] == "ready" and inst["ready"] is True and inst["ready_since"]
        assert inst["active_state"] == "active" and inst["sub_state"] == "running" and inst["enabled"] is True
        assert inst["container"]["id"] == container_id(host, f"isaac-sim-{i}")
        # the release's healthcheck: NVIDIA's AppReady check and the signal port answering
        assert inst["container"]["state"] == "running" and inst["container"]["health"] == "healthy"
        assert inst["health"] == "healthy"
        assert 0 <= inst["uptime_s"] < 24 * 3600
        assert inst["digest"] == digest.stdout.strip().split("@", 1)[1]
        assert inst["ports"] == {"signal": 49100 + i, "stream": 47998 + i, "web_viewer": 8210 + i}
        # the block keeps the web viewer's port, but no viewer runs in this scenario (test_web_viewer
        # deploys them): no URL is given for what nothing serves
        assert inst["urls"] == {"signal": f"{ip}:{49100 + i}", "stream": f"{ip}:{47998 + i}/udp"}
        assert inst["gpu"] is None and inst["limits"] == {"memory": "1g", "shm_size": "256m"}
        # the signal address the URL names is the instance's own
        with socket.create_connection((ip, 49100 + i), timeout=2) as conn:
            conn.sendall(b"hello\n")  # the stand-in's hook for tests
            assert conn.recv(64).startswith(b"isaac-sim-standin")
    # fixed cost: one systemctl show, one journalctl for the last day's ends, no nvidia-smi on this
    # host, two Docker API calls
    assert result["cost"] == {"spawns": 2, "docker_api_calls": 2}
    kinds = {"session_ends", "crashes", "unhealthy_restarts", "docker_away"}
    assert all(set(i["last_day"]) == kinds for i in result["instances"])


def test_status_says_how_long_each_start_took_to_ready_and_whether_its_caches_were_warm(host):
    caches = "/var/lib/isaac-sim/instance-3/cache"

    def three():
        all_ready(host, [3])
        return by_name(testbed.info(host))["isaac-sim-3"]

    # a start on empty caches (a new host, release or driver): cold, and the stand-in takes its cold
    # time (3 s, 1 s on a warm cache); the cache directories themselves stay, as the role made them.
    # Each start by hand flushes the unit's start-limit counter first, as the day-2 playbook does
    # (this scenario allows 3 starts in its interval, and the tests after this one start it again).
    sh(host, f"systemctl stop isaac-sim@3 && find {caches} -mindepth 2 -delete")
    sh(host, "systemctl reset-failed isaac-sim@3; systemctl start isaac-sim@3")
    cold = three()
    assert cold["cache_at_start"] == "cold" and cold["ready_after_s"] >= 3, cold
    said = sh(host, "journalctl -u isaac-sim@3 -n 200 --no-pager | grep 'starting as' | tail -n 1").stdout
    assert "shader cache cold" in said, said
    sh(host, "systemctl reset-failed isaac-sim@3; systemctl restart isaac-sim@3")
    warm = three()
    sh(host, "systemctl reset-failed isaac-sim@3")
    assert warm["cache_at_start"] == "warm" and warm["ready_after_s"] >= 1, warm
    # every instance, from its container's start to the ready line the gate saw, with the caches the
    # stand-in itself says it found at that start (cold where the scenario's converge was its first)
    for inst in testbed.info(host)["instances"]:
        last = sh(host, f"journalctl -u {inst['unit']} -n 200 --no-pager | grep 'starting as' | tail -n 1").stdout
        assert f"shader cache {inst['cache_at_start']})" in last, (inst, last)
        assert 1 <= inst["ready_after_s"] <= inst["uptime_s"] + 1, inst


def test_info_in_check_mode_and_with_log_lines(host):
    result = testbed.info(host, check=True, log_lines=5, instances=[1])
    assert result["changed"] is False
    assert [i["name"] for i in result["instances"]] == ["isaac-sim-1"]
    logs = result["instances"][0]["logs"]
    assert 1 <= len(logs) <= 5 and any("is loaded" in line or "is ready" in line for line in logs)
    assert result["cost"]["spawns"] == 3  # + one journalctl for all asked units


def test_a_stopped_instance_reports_stopped(host):
    sh(host, "systemctl stop isaac-sim@3")
    try:
        inst = by_name(testbed.info(host))["isaac-sim-3"]
        assert inst["state"] == "stopped" and inst["ready"] is False and inst["container"] is None
        assert inst["active_state"] == "inactive" and inst["enabled"] is True
        assert inst["down_reason"].startswith("stopped: ")
    finally:
        sh(host, "systemctl start isaac-sim@3")
    all_ready(host, [3])


def test_a_crashed_instance_shows_its_restarts(host):
    before = int(unit_show(host, "isaac-sim@1.service")["NRestarts"])
    sh(host, "docker kill isaac-sim-1")
    wait_for(lambda: int(unit_show(host, "isaac-sim@1.service")["NRestarts"]) > before, what="a restart")
    all_ready(host, [1])
    inst = by_name(testbed.info(host))["isaac-sim-1"]
    assert inst["restarts"] >= 1 and inst["restarts"] == before + 1
    assert inst["ready"] is True


def test_a_stray_container_is_reported(host):
    image = by_name(testbed.info(host))["isaac-sim-0"]["image"]
    sh(host, f"docker run -d --rm --name isaac-sim-9 --network none --entrypoint sleep {image} 600")
    try:
        result = testbed.info(host)
        stray = by_name(result)["isaac-sim-9"]
        assert stray["stray"] and not stray["configured"] and stray["state"] == "stray-container"
        assert stray["container"]["state"] == "running" and stray["unit"] is None and stray["ready"] is False
        assert result["summary"]["stray"] == 1 and result["summary"]["configured"] == 4
    finally:
        sh(host, "docker rm -f isaac-sim-9")


def test_a_starting_instance_is_not_ready_and_a_day2_restart_fixes_it(host):
    others = {i: container_id(host, f"isaac-sim-{i}") for i in (0, 1, 3)}
    old = container_id(host, "isaac-sim-2")
    # behind the role's back: instance 2 never prints its ready line
    sh(
        host,
        "sed -i 's/^ISAAC_SIM_DOCKER_ARGS=\"/ISAAC_SIM_DOCKER_ARGS=\"--env=STANDIN_NEVER_READY=1 /' "
        "/etc/isaac-sim/instance-2.env && systemctl restart --no-block isaac-sim@2",
    )
    try:
        # the new container, not the old one on its way out, and running, not only created
        wait_for(lambda: container_id(host, "isaac-sim-2") not in ("", old), what="the new container of instance 2")

        def running():
            found = by_name(testbed.info(host))["isaac-sim-2"]
            return found if (found["container"] or {}).get("state") == "running" else None

        inst = wait_for(running, what="instance 2's new container running")
        assert inst["ready"] is False and inst["state"] == "starting"
    finally:
        # put the file back as the role wrote it, whatever happened, and restart through the day-2 playbook
        sh(host, "sed -i 's/--env=STANDIN_NEVER_READY=1 //' /etc/isaac-sim/instance-2.env")
    run = ok(
        testbed.run_playbook(
            host,
            {"isaac_sim_action": "restart", "isaac_sim_instances_selected": [2]},
            playbook="playbooks/instance.yml",
        )
    )
    assert testbed.changed_count(run, host) >= 1
    assert by_name(testbed.info(host))["isaac-sim-2"]["ready"] is True
    assert {i: container_id(host, f"isaac-sim-{i}") for i in (0, 1, 3)} == others


@pytest.mark.core
def test_status_playbook_prints_the_table_and_writes_json(host, tmp_path, ip):
    run, out = dashboard(host, tmp_path)
    table = (out / "status.txt").read_text().splitlines()
    assert table[0].split() == ["HOST", "INSTANCE", "STATE", "READY", "UPTIME", "RESTARTS", "GPU", "URL"]
    rows = [line.split() for line in table[1:-1]]
    # one line per instance (companions get lines of their own: test_web_viewer)
    assert [(r[0], r[1], r[2], r[3], r[-1]) for r in rows] == [
        (testbed.name(host), str(i), "ready", "yes", f"{ip}:{49100 + i}") for i in range(INSTANCES)
    ]
    assert table[0] in run.stdout  # also printed by the play
    report = json.loads((out / "status.json").read_text())
    assert report["summary"]["instances"] == INSTANCES and report["summary"]["ready"] == INSTANCES


def status_request(url, method="GET", origin=None):
    request = urllib.request.Request(url, method=method, headers={"Origin": origin} if origin else {})
    try:
        with urllib.request.urlopen(request, timeout=5) as response:
            return response.status, dict(response.headers), response.read()
    except urllib.error.HTTPError as exc:
        return exc.code, dict(exc.headers), exc.read()


def test_each_host_serves_its_status_read_only_to_the_networks_allowed(host, ip):
    url = f"http://{ip}:8290/status"
    info = testbed.info(host)
    assert info["status_url"] == url
    code, headers, body = status_request(url, origin="null")
    # readable by the dashboard opened as a file, not by any web site the operator visits
    assert code == 200 and headers["Access-Control-Allow-Origin"] == "null"
    assert "Access-Control-Allow-Origin" not in status_request(url, origin="https://evil.example")[1]
    live = json.loads(body)
    # the host as the dashboard draws it, from the same status code as isaac_sim_info
    assert live["host"] == testbed.name(host) and live["reachable"] and live["status_url"] == url
    assert [(i["name"], i["state"], i["ports"]) for i in live["instances"]] == [
        (i["name"], i["state"], i["ports"]) for i in info["instances"]
    ]
    assert all(i["uptime"] and "gpu_text" in i for i in live["instances"])
    # read-only: nothing but GET
    assert status_request(url, "POST")[0] == 405 and status_request(url, "DELETE")[0] == 405
    assert status_request(f"http://{ip}:8290/")[0] == 404
    # every address (the allow list decides who reads); no capability, a read-only system
    assert sh(host, "ss -Hltn 'sport = :8290'").stdout.split()[3] in ("0.0.0.0:8290", "*:8290")
    props = sh(host, "systemctl show isaac-sim-status -p CapabilityBoundingSet,NoNewPrivileges,ProtectSystem").stdout
    assert set(props.split()) == {"CapabilityBoundingSet=", "NoNewPrivileges=yes", "ProtectSystem=strict"}
    testbed.assert_sandboxed(host, "isaac-sim-status.service")
    before = {i: container_id(host, f"isaac-sim-{i}") for i in range(INSTANCES)}
    try:
        ok(testbed.run_playbook(host, {"isaac_sim_status_server_allow": ["10.255.0.0/16"]}))
        code, _headers, body = status_request(url)
        assert code == 403 and b"isaac_sim_status_server_allow" in body
        # turned off: the unit and its files go, and isaac_sim_info says there is no live status
        ok(testbed.run_playbook(host, {"isaac_sim_status_server_enabled": False}))
        assert sh(host, "test -e /etc/systemd/system/isaac-sim-status.service", check=False).rc != 0
        assert sh(host, "ss -Hltn 'sport = :8290' | wc -l").stdout.strip() == "0"
        assert testbed.info(host)["status_url"] is None
    finally:
        ok(testbed.run_playbook(host))
    assert status_request(url)[0] == 200
    # the endpoint is a host service: its changes restart no instance
    assert {i: container_id(host, f"isaac-sim-{i}") for i in range(INSTANCES)} == before
    # a re-run leaves out the endpoint's module call where the plan found it as wanted (by digests): one
    # of its files changed by hand, or the unit stopped, is each put back all the same
    layout = "/usr/local/lib/isaac-sim/status/layout.py"
    sh(host, f"echo '# changed by hand' >> {layout}")
    mended = ok(testbed.run_playbook(host))
    assert testbed.changed_count(mended, host) == 1 and "changed by hand" not in sh(host, f"cat {layout}").stdout
    sh(host, f"chmod 0600 {layout} && systemctl stop isaac-sim-status")
    mended = ok(testbed.run_playbook(host))
    assert testbed.changed_count(mended, host) == 1 and sh(host, f"stat -c %a {layout}").stdout.strip() == "644"
    assert sh(host, "systemctl is-active isaac-sim-status").stdout.strip() == "active"
    assert status_request(url)[0] == 200
    # and as wanted, the next run makes no call for it (the plan read every file the module would write)
    again = ok(testbed.run_playbook(host)).stdout
    assert re.search(r"Serve this host's status read-only[^\n]*\*+\nskipping: ", again), again[-3000:]


def test_the_dashboard_follows_each_host_live_without_ansible(host, tmp_path):
    _run, out = dashboard(host, tmp_path, {"fleet_report_refresh": 1})
    with chromium() as driver:
        driver.get((out / "status.html").as_uri())

        def section():
            return driver.find_element("css selector", "section.host")

        def state(i):
            return driver.find_element("css selector", f'.instance-card[data-instance="{i}"]').get_attribute(
                "data-state"
            )

        wait_for(lambda: section().get_attribute("data-live") == "ok", timeout=15, what="the page to read the host")
        sh(host, "systemctl stop isaac-sim@1")
        try:
            wait_for(lambda: state(1) == "stopped", timeout=15, interval=0.5, what="instance 1 shown stopped")
            assert driver.find_element("id", "sum-ready").text == str(INSTANCES - 1)
        finally:
            sh(host, "systemctl start isaac-sim@1")
        wait_for(lambda: state(1) == "ready", timeout=60, interval=0.5, what="instance 1 shown ready again")
        assert driver.find_element("id", "sum-ready").text == str(INSTANCES)
        # a host that stops answering is shown as unreachable, its cards kept as last known
        sh(host, "systemctl stop isaac-sim-status")
        try:
            wait_for(lambda: section().get_attribute("data-live") == "unreachable", timeout=15, what="unreachable")
            assert "unreachable" in section().find_element("css selector", ".host-line").text
            assert len(driver.find_elements("css selector", ".instance-card")) == INSTANCES
        finally:
            sh(host, "systemctl start isaac-sim-status")
        wait_for(lambda: section().get_attribute("data-live") == "ok", timeout=20, what="the host back")
        driver.save_screenshot(str(OUTPUT / "dashboard-live.png"))
    all_ready(host)


def test_an_open_dashboard_shows_a_rollout_s_new_image_without_a_reload(host, tmp_path):
    # one renderer draws the page from the snapshot and from every live answer: what a rollout
    # changes (image, digest) appears on a page opened before it
    old, new = testbed.registry_image(host, "6.0.1"), testbed.registry_image(host, "6.0.2")
    _run, out = dashboard(host, tmp_path, {"fleet_report_refresh": 1})
    with chromium() as driver:
        driver.get((out / "status.html").as_uri())

        def images(what="textContent"):
            # in one script: the page redraws a card's fields on every refresh, so an element
            # found in one call may be gone by the next
            return driver.execute_script(
                "var what = arguments[0];"
                "return Array.from(document.querySelectorAll('.instance-card .f-image code'))"
                ".map(function (code) { return code[what]; });",
                what,
            )

        assert len(images()) == INSTANCES and all(text.startswith(old + " @") for text in images()), images()
        wait_for(
            lambda: driver.find_element("css selector", "section.host").get_attribute("data-live") == "ok",
            timeout=15,
            what="the page to read the host",
        )

        def rolled_on_every_card():
            found = images()
            return len(found) == INSTANCES and all(text.startswith(new + " @") for text in found)

        marker = driver.execute_script("window.sameDocument = 'yes'; return window.sameDocument")
        try:
            rolled = testbed.run_playbook(host, {"isaac_sim_image": new})
            assert rolled.returncode == 0, rolled.stdout[-3000:]
            wait_for(
                rolled_on_every_card,
                timeout=30,
                interval=0.5,
                what="the new image on every card",
            )
            assert driver.execute_script("return window.sameDocument") == marker  # never reloaded
            digests = set(images("title"))
            assert all(d.startswith("sha256:") for d in digests), digests
            driver.save_screenshot(str(OUTPUT / "dashboard-rollout.png"))
        except BaseException:
            # the scenario's image back for the tests after this one's failure; passed, the new image
            # stays: no later test of this module asks for the image, and test_remove_and_cleanup's
            # redeploy (of the scenario's settings) puts it back
            assert testbed.run_playbook(host).returncode == 0
            raise
    all_ready(host)


def test_dashboard_in_headless_chromium(host, tmp_path):
    _first, out = dashboard(host, tmp_path)
    expected = {i["id"]: i for i in testbed.info(host)["instances"]}
    found = check_dashboard(out / "status.html", expected, OUTPUT / "dashboard.png")
    assert found["links"] == []  # 6.x links its web viewers only where they run (test_web_viewer)
    assert {kind for _addr, kind, _port in found["addresses"]} == {"signal", "stream"}
    assert found["frames"] == []  # 6.x serves no browser client of its own


def test_markup_in_names_is_shown_as_text_and_never_runs(host, tmp_path):
    evil = "<img src=x onerror=\"document.body.dataset.pwned='yes'\">"
    _run, out = dashboard(
        host,
        tmp_path,
        {
            "fleet_report_title": "Lab " + evil,
            "isaac_sim_status_public_address": "gpu" + evil,
            "fleet_report_refresh": 0,
        },
    )
    with chromium() as driver:
        driver.get((out / "status.html").as_uri())
        time.sleep(1)
        assert driver.find_elements("css selector", "img") == []
        assert driver.execute_script("return document.body.dataset.pwned || ''") == ""
        assert driver.title == "Lab " + evil
        assert driver.find_element("tag name", "h1").text == "Lab " + evil
        assert "gpu" + evil in driver.find_element("css selector", "code.stream-address").text
        driver.save_screenshot(str(OUTPUT / "dashboard-markup.png"))


def test_day2_actions_refuse_bad_input_before_any_change(host):
    before = testbed.snapshot(host)
    for extra, message in (
        ({"isaac_sim_action": "bounce"}, "isaac_sim_action: 'bounce' is not one of start, stop, restart, remove. Fix:"),
        (
            {"isaac_sim_action": "restart", "isaac_sim_instances_selected": [7]},
            "isaac_sim_instances_selected: 7 not configured",
        ),
    ):
        run = testbed.run_playbook(host, extra, playbook="playbooks/instance.yml")
        assert run.returncode != 0
        # argument-spec errors go to stderr, assert messages to stdout
        assert message in re.sub(r"\s+", " ", run.stdout + run.stderr), run.stdout[-2000:] + run.stderr
        assert testbed.changed_count(run, host) == 0
    assert testbed.snapshot(host) == before


def test_day2_stop_start_and_logs(host):
    ids = {i: container_id(host, f"isaac-sim-{i}") for i in range(INSTANCES)}
    ok(
        testbed.run_playbook(
            host,
            {"isaac_sim_action": "stop", "isaac_sim_instances_selected": [0, 1]},
            playbook="playbooks/instance.yml",
        )
    )
    result = by_name(testbed.info(host))
    assert [result[f"isaac-sim-{i}"]["state"] for i in range(INSTANCES)] == ["stopped", "stopped", "ready", "ready"]
    assert result["isaac-sim-0"]["enabled"] is True  # stop is not remove: it comes back at boot
    ok(testbed.run_playbook(host, {"isaac_sim_action": "start"}, playbook="playbooks/instance.yml"))
    result = by_name(testbed.info(host))
    assert all(result[f"isaac-sim-{i}"]["ready"] for i in range(INSTANCES))
    assert [container_id(host, f"isaac-sim-{i}") for i in (2, 3)] == [ids[2], ids[3]]
    logs = ok(testbed.run_playbook(host, {"isaac_sim_log_lines": 4}, playbook="playbooks/logs.yml"))
    for i in range(INSTANCES):
        assert f"== isaac-sim-{i} (ready)" in logs.stdout
    assert logs.stdout.count("App is loaded.") >= INSTANCES


def test_remove_and_cleanup_keep_caches_and_foreign_containers(host):
    image = by_name(testbed.info(host))["isaac-sim-0"]["image"]
    ok(
        testbed.run_playbook(
            host, {"isaac_sim_action": "remove", "isaac_sim_instances_selected": [3]}, playbook="playbooks/instance.yml"
        )
    )
    assert sh(host, "test -e /etc/isaac-sim/instance-3.env", check=False).rc != 0
    assert sh(host, "systemctl is-enabled isaac-sim@3", check=False).stdout.strip() != "enabled"
    assert sh(host, "test -d /var/lib/isaac-sim/instance-3/cache", check=False).rc == 0
    assert [i["id"] for i in testbed.info(host)["instances"]] == [0, 1, 2]
    sh(host, f"docker run -d --name not-ours --network none --entrypoint sleep {image} 600")
    # a port the site reserved itself, after the deploy: the collection never takes it away
    reserved = "/proc/sys/net/ipv4/ip_local_reserved_ports"
    sh(host, f"echo $(cat {reserved}),9999 > {reserved}")
    try:
        cleanup = ok(testbed.run_playbook(host, playbook="playbooks/cleanup.yml"))
        assert "caches, logs and data stay" in cleanup.stdout
        assert sh(host, f"cat {reserved}").stdout.strip() == "9999"
        assert sh(host, "ls /etc/sysctl.d/ | grep -c isaac-sim", check=False).stdout.strip() == "0"
        assert sh(host, "ls /etc/systemd/system/ | grep -c isaac-sim", check=False).stdout.strip() == "0"
        assert sh(host, "find /etc/systemd/system -name 'isaac-sim*'", check=False).stdout.strip() == ""
        # no rule of the collection's left; Docker's tables stay
        tables = sh(host, "nft list tables").stdout
        assert "isaac_sim" not in tables and "table ip filter" in tables
        assert sh(host, "docker ps -q --filter name=isaac-sim-", check=False).stdout.strip() == ""
        assert container_id(host, "not-ours")
        for i in range(INSTANCES):
            assert sh(host, f"test -d /var/lib/isaac-sim/instance-{i}/cache", check=False).rc == 0
        # a host without a deployment: every day-2 action refuses, nothing changes
        before = testbed.snapshot(host)
        run = testbed.run_playbook(host, {"isaac_sim_action": "start"}, playbook="playbooks/instance.yml")
        assert run.returncode != 0 and "Isaac Sim is not deployed on" in run.stdout + run.stderr
        assert testbed.snapshot(host) == before
        again = ok(testbed.run_playbook(host, playbook="playbooks/cleanup.yml"))
        assert testbed.changed_count(again, host) == 0
    finally:
        sh(host, "docker rm -f not-ours", check=False)
        sh(host, f"echo > {reserved}")
    # redeploy with metrics on: all four back, warm caches
    ok(testbed.run_playbook(host, {"isaac_sim_metrics_enabled": True, "isaac_sim_metrics_interval": "5s"}))
    all_ready(host)


def test_metrics_timer_writes_prometheus_text_and_goes_away_when_off(host):
    prom = "/var/lib/prometheus/node-exporter/isaac_sim.prom"
    wait_for(lambda: sh(host, f"test -s {prom}", check=False).rc == 0, what="the metrics file")
    sh(host, "systemctl stop isaac-sim@2")
    try:
        stamp = sh(host, f"stat -c %Y {prom}").stdout
        wait_for(lambda: sh(host, f"stat -c %Y {prom}").stdout != stamp, timeout=30, what="a fresh metrics file")
        text = sh(host, f"cat {prom}").stdout
        for i in (0, 1, 3):
            assert f'isaac_sim_up{{isaac_sim_instance="{i}"}} 1' in text
            assert f'isaac_sim_ready{{isaac_sim_instance="{i}"}} 1' in text
            assert re.search(rf'isaac_sim_uptime_seconds{{isaac_sim_instance="{i}"}} \d+', text)
            assert re.search(rf'isaac_sim_ready_seconds{{isaac_sim_instance="{i}",cache="warm"}} \d+', text)
        assert 'isaac_sim_up{isaac_sim_instance="2"} 0' in text
        assert 'isaac_sim_ready{isaac_sim_instance="2"} 0' in text
        assert 'isaac_sim_restarts{isaac_sim_instance="0"} 0' in text
        assert sh(host, "systemctl is-enabled isaac-sim-metrics.timer").stdout.strip() == "enabled"
        # it wrote the file above from its sandbox
        testbed.assert_sandboxed(host, "isaac-sim-metrics.service")
    finally:
        sh(host, "systemctl start isaac-sim@2")
    ok(testbed.run_playbook(host, {"isaac_sim_metrics_enabled": False}))
    assert sh(host, f"test -e {prom}", check=False).rc != 0
    assert sh(host, "test -e /etc/systemd/system/isaac-sim-metrics.timer", check=False).rc != 0
    # a run of the oneshot stopped mid-way is not left in `systemctl --failed` as "not-found failed"
    assert "isaac-sim-metrics" not in sh(host, "systemctl --failed --no-legend --plain").stdout
    all_ready(host)
