"""NVIDIA's Hub Workstation Cache, one per host for its 6.x instances (isaac_sim_hub_cache_enabled).

The Hub image cannot be pulled here: the stand-in of tests/fixtures/hub-cache (a test fixture:
user 1234, port 14090, a settings page, a file in its cache) comes from the local registry.
The module turns the Hub on with its first deploy and off again with its last test.
"""

import pytest
import testbed
from testbed import INSTANCES, all_ready, by_name, container_id, sh, unit_show

HUB_DIR = "/var/lib/isaac-sim/hub-cache"


def ok(result):
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr
    return result


@pytest.fixture(scope="module")
def hub(host):
    image = testbed.registry_image(host, "6.0.1").replace("isaac-sim-standin:6.0.1", "hub-workstation-cache:2.0.0")
    extra = {"isaac_sim_hub_cache_enabled": True, "isaac_sim_hub_cache_image": image}
    ok(testbed.run_playbook(host, extra))
    all_ready(host)
    return extra


def mounts(host, i) -> dict:
    out = sh(
        host, f"docker inspect -f '{{{{range .Mounts}}}}{{{{.Destination}}}}={{{{.Source}}}} {{{{end}}}}' isaac-sim-{i}"
    )
    return dict(pair.split("=", 1) for pair in out.stdout.split())


def test_one_hub_per_host_started_before_the_instances_that_share_its_directory(host, hub):
    show = unit_show(host, "isaac-sim-hub.service")
    assert show["ActiveState"] == "active" and show["UnitFileState"] == "enabled"
    inspect = sh(host, "docker inspect -f '{{.Config.User}} {{.HostConfig.NetworkMode}}' isaac-sim-hub").stdout.split()
    assert inspect == ["1234:1234", "host"]
    assert "Hub settings" in sh(host, "curl -sf http://127.0.0.1:14090/index.html").stdout
    # one directory, the Hub's and every instance's, owned by NVIDIA's user
    assert sh(host, f"stat -c '%u:%g' {HUB_DIR}").stdout.strip() == "1234:1234"
    for i in range(INSTANCES):
        assert mounts(host, i)["/var/cache/hub"] == HUB_DIR
    assert "as uid 1234" in sh(host, "docker exec isaac-sim-0 cat /var/cache/hub/hub-standin.log").stdout
    # the instances want it and start after it (a drop-in for the template)
    deps = sh(host, "systemctl show isaac-sim@2 -p Wants -p After").stdout
    assert deps.count("isaac-sim-hub.service") == 2
    status = testbed.info(host)
    assert status["summary"]["stray"] == 0 and "isaac-sim-hub" not in by_name(status)
    assert [(s["name"], s["state"]) for s in status["host_services"]] == [("hub", "running")]
    # the host side of every unit of an instance's host sandboxed as the security guide lists it
    testbed.assert_sandboxed(host, "isaac-sim-hub.service")
    testbed.assert_sandboxed(host, "isaac-sim@0.service", "isaac-sim@.service")
    testbed.assert_sandboxed(host, "isaac-sim-firewall.service")
    # a second run changes nothing, the Hub included
    hub_id = container_id(host, "isaac-sim-hub")
    assert testbed.changed_count(ok(testbed.run_playbook(host, hub)), host) == 0
    assert container_id(host, "isaac-sim-hub") == hub_id


def test_a_hub_restart_keeps_its_cache_and_every_instance(host, hub):
    before = {i: container_id(host, f"isaac-sim-{i}") for i in range(INSTANCES)}
    sh(host, "systemctl restart isaac-sim-hub")
    assert sh(host, f"grep -c started {HUB_DIR}/hub-standin.log").stdout.strip() == "2"
    assert {i: container_id(host, f"isaac-sim-{i}") for i in range(INSTANCES)} == before


def test_turning_the_hub_off_removes_its_unit_and_keeps_its_cache(host, hub):
    ok(testbed.run_playbook(host))
    all_ready(host)
    assert container_id(host, "isaac-sim-hub") == ""
    for path in ("isaac-sim-hub.service", "isaac-sim@.service.d/hub.conf"):
        assert sh(host, f"test -e /etc/systemd/system/{path}", check=False).rc != 0
    assert "isaac-sim-hub" not in sh(host, "systemctl show isaac-sim@2 -p Wants").stdout
    # the cache stays; each instance has its own Hub cache again, as NVIDIA's compose recipe has
    assert sh(host, f"test -s {HUB_DIR}/hub-standin.log", check=False).rc == 0
    for i in range(INSTANCES):
        assert mounts(host, i)["/var/cache/hub"] == f"/var/lib/isaac-sim/instance-{i}/cache/hub"
