"""Companions: containers bound to an instance, each a systemd unit of its own.

Runs on the molecule default host (four 6.x stand-in instances). The companion is a
small HTTP server (Python's, in the stand-in image) with a healthcheck and a kept
volume; the last test deploys the scenario's own settings again, without companions.
"""

import json
import urllib.request

import pytest
import testbed
from testbed import INSTANCES, all_ready, by_name, container_id, sh, unit_show, wait_for

REC_UNIT = "/etc/systemd/system/isaac-sim-rec@.service"
WITH_REC = [1, 3]


@pytest.fixture()
def ip(host):
    return testbed.host_ip(host)


@pytest.fixture()
def rec(host):
    """A recorder-like companion of instances 1 and 3: serves its kept /data on its own port of
    the block, healthchecked."""
    return {
        "name": "rec",
        "instances": WITH_REC,
        "image": testbed.registry_image(host, "6.0.1"),
        "entrypoint": "python3",
        "command": ["-m", "http.server", "{port.http}", "--bind", "{host}", "--directory", "/data"],
        "ports": {"http": 9100},
        "volumes": ["recordings:/data"],
        "env": {"REC_INSTANCE": "{instance}"},
        "healthcheck": {
            "test": ["CMD", "python3", "-c", "import urllib.request as u; u.urlopen('http://{host}:{port.http}/')"],
            "interval": 2,
        },
    }


def ok(result):
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr
    return result


def monotonic(host, unit, prop):
    return int(sh(host, f"systemctl show -p {prop} --value {unit}").stdout.strip() or 0)


def answers(ip, port):
    with urllib.request.urlopen(f"http://{ip}:{port}/", timeout=3) as response:
        return response.status == 200


def test_a_companion_starts_once_its_instance_is_ready_and_shows_under_it(host, ip, rec):
    ok(testbed.run_playbook(host, {"isaac_sim_companions": [rec]}))
    status = testbed.info(host)
    assert status["summary"]["stray"] == 0 and status["summary"]["ready"] == INSTANCES
    for i in (0, 2):
        assert "rec" not in {c["name"] for c in by_name(status)[f"isaac-sim-{i}"]["companions"]}
        assert container_id(host, f"isaac-sim-{i}-rec") == ""
    for i in WITH_REC:
        unit = f"isaac-sim-rec@{i}.service"
        show = unit_show(host, unit)
        assert show["ActiveState"] == "active" and show["UnitFileState"] == "enabled"
        # started after its instance became active, which is after the readiness gate passed
        assert monotonic(host, unit, "ExecMainStartTimestampMonotonic") >= monotonic(
            host, f"isaac-sim@{i}.service", "ActiveEnterTimestampMonotonic"
        )
        assert answers(ip, 9100 + i)
        env = sh(host, f"docker exec isaac-sim-{i}-rec env").stdout.splitlines()
        assert f"REC_INSTANCE={i}" in env and f"ISAAC_SIM_HOST={ip}" in env and f"ISAAC_SIM_PORT_HTTP={9100 + i}" in env
        labels = json.loads(sh(host, f"docker inspect -f '{{{{json .Config.Labels}}}}' isaac-sim-{i}-rec").stdout)
        assert labels["org.isaacsim.fleet.instance"] == str(i) and labels["org.isaacsim.fleet.companion"] == "rec"
        comp = {c["name"]: c for c in by_name(status)[f"isaac-sim-{i}"]["companions"]}["rec"]
        assert comp["state"] == "ready" and comp["health"] == "healthy"
        assert comp["ports"] == [{"proto": "tcp", "port": 9100 + i}] and comp["unit"] == unit
    testbed.assert_sandboxed(host, f"isaac-sim-rec@{WITH_REC[0]}.service", "isaac-sim-NAME@.service")
    # a second run changes nothing
    assert testbed.changed_count(ok(testbed.run_playbook(host, {"isaac_sim_companions": [rec]})), host) == 0


def test_a_companion_that_never_gets_healthy_reverts_its_instance_and_stops_the_deploy(host, rec):
    before = {i: container_id(host, f"isaac-sim-{i}") for i in range(INSTANCES)}
    bad = {
        "name": "bad",
        "image": rec["image"],
        "entrypoint": "sleep",
        "command": ["600"],
        "healthcheck": {"test": "exit 1", "interval": 1, "retries": 1},
        "ready_timeout": 5,
    }
    result = testbed.run_playbook(host, {"isaac_sim_companions": [rec, bad]})
    assert result.returncode != 0
    # Ansible wraps long messages: compare with every run of whitespace made one space
    out = " ".join((result.stdout + result.stderr).split())
    assert "isaac-sim-0: its companion isaac-sim-0-bad did not start" in out, result.stdout[-3000:]
    assert "was not ready within 5 s" in out
    # the companion's own words, not the pre-start cleanup's
    assert "No such container" not in out
    all_ready(host)
    # no failed unit left behind (host degraded, a stray in status)
    failed = sh(host, "systemctl list-units --failed --all --plain --no-legend 'isaac-sim*'").stdout
    assert failed.strip() == "", failed
    # instance 0 is back on its previous set (no companion); the others were not touched
    assert all(container_id(host, f"isaac-sim-{i}") == before[i] for i in (1, 2, 3))
    assert sh(host, "ls /etc/isaac-sim/ | grep -c '\\.bad\\.env'", check=False).stdout.strip() == "0"
    assert unit_show(host, "isaac-sim-bad@0.service")["UnitFileState"] != "enabled"
    assert [c["name"] for c in by_name(testbed.info(host))["isaac-sim-0"]["companions"]] == []
    assert sh(host, "test -e /etc/systemd/system/isaac-sim-bad@.service", check=False).rc != 0


def test_a_companion_restarts_with_its_instance_and_keeps_its_volume(host, ip):
    sh(host, "docker exec isaac-sim-1-rec sh -c 'echo take-1 > /data/take.txt'")
    comp_before = container_id(host, "isaac-sim-1-rec")
    entered = monotonic(host, "isaac-sim@1.service", "ActiveEnterTimestampMonotonic")
    # the instance dies; systemd brings it back and the companion with it (PartOf=, WantedBy=)
    sh(host, "docker kill isaac-sim-1")
    wait_for(
        lambda: monotonic(host, "isaac-sim@1.service", "ActiveEnterTimestampMonotonic") > entered
        and testbed.instance_ready(host, 1),
        what="isaac-sim@1 back",
    )
    wait_for(lambda: unit_show(host, "isaac-sim-rec@1.service")["ActiveState"] == "active", what="rec@1 back")
    comp_after = container_id(host, "isaac-sim-1-rec")
    assert comp_after and comp_after != comp_before
    assert monotonic(host, "isaac-sim-rec@1.service", "ExecMainStartTimestampMonotonic") >= monotonic(
        host, "isaac-sim@1.service", "ActiveEnterTimestampMonotonic"
    )
    with urllib.request.urlopen(f"http://{ip}:9101/take.txt", timeout=3) as response:
        assert response.read() == b"take-1\n"
    # a companion that dies alone comes back alone: its instance is not restarted
    instance, alone = container_id(host, "isaac-sim-3"), container_id(host, "isaac-sim-3-rec")
    sh(host, "docker kill isaac-sim-3-rec")
    wait_for(
        lambda: container_id(host, "isaac-sim-3-rec") not in ("", alone) and answers(ip, 9103),
        what="rec@3 back",
    )
    assert container_id(host, "isaac-sim-3") == instance


def test_scale_down_takes_the_companion_with_its_instance(host, rec):
    ok(testbed.run_playbook(host, {"isaac_sim_companions": [rec], "isaac_sim_instance_count": 3}))
    show = unit_show(host, "isaac-sim-rec@3.service")
    assert show["ActiveState"] == "inactive" and show["UnitFileState"] != "enabled"
    assert container_id(host, "isaac-sim-3-rec") == ""
    assert sh(host, "test -e /etc/isaac-sim/instance-3.rec.env", check=False).rc != 0
    # its kept data stays, as the instance's caches do
    assert sh(host, "test -d /var/lib/isaac-sim/instance-3/companions/rec/recordings", check=False).rc == 0
    status = testbed.info(host)
    assert status["summary"]["stray"] == 0 and "isaac-sim-3" not in by_name(status)


def test_taking_the_companion_away_removes_its_units_and_template(host):
    ok(testbed.run_playbook(host))
    all_ready(host)
    assert sh(host, "docker ps -a --format '{{.Names}}' | grep -c -- '-rec$'", check=False).stdout.strip() == "0"
    assert sh(host, f"test -e {REC_UNIT}", check=False).rc != 0
    assert sh(host, "ls /etc/isaac-sim/ | grep -c '\\.rec\\.env'", check=False).stdout.strip() == "0"
    loaded = sh(host, "systemctl list-units --all --no-legend 'isaac-sim-rec@*' | grep -c rec", check=False)
    assert loaded.stdout.strip() == "0"
    # no companion is left (the scenario runs no web viewer: test_web_viewer deploys them)
    assert [c for inst in testbed.info(host)["instances"] for c in inst["companions"]] == []
    # the recordings were kept
    assert sh(host, "cat /var/lib/isaac-sim/instance-1/companions/rec/recordings/take.txt").stdout == "take-1\n"
