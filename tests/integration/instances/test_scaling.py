"""Scaling down removes instances and keeps their caches; scaling up again starts warm."""

import testbed
from testbed import INSTANCES, container_id, sh, unit_show


def test_scale_4_to_2_removes_two_instances_and_keeps_their_caches(host):
    kept = {i: container_id(host, f"isaac-sim-{i}") for i in (0, 1)}
    # every instance of a serving host down: only when confirmed
    before = testbed.snapshot(host)
    refused = testbed.run_playbook(host, {"isaac_sim_instance_count": 0})
    said = " ".join((refused.stdout + refused.stderr).split())
    assert refused.returncode != 0 and "isaac_sim_instance_count: 0 stops and removes every instance" in said, said[
        -3000:
    ]
    assert "Fix: set isaac_sim_scale_to_zero: true" in said and testbed.snapshot(host) == before
    result = testbed.run_playbook(host, {"isaac_sim_instance_count": 2})
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr
    # serving instances removed in the rollout's canary batches, as any change of serving instances
    assert "TASK [Roll this batch's hosts, one instance at a time on each]" in result.stdout, result.stdout[-3000:]
    for i in (2, 3):
        show = unit_show(host, f"isaac-sim@{i}.service")
        assert show["ActiveState"] == "inactive"
        assert show["UnitFileState"] == "disabled"
        assert container_id(host, f"isaac-sim-{i}") == ""
        assert sh(host, f"test -e /etc/isaac-sim/instance-{i}.env", check=False).rc != 0
        # the cache the instance wrote while it ran is still there
        assert (
            sh(host, f"test -s /var/lib/isaac-sim/instance-{i}/cache/main/ov/standin-shader-cache", check=False).rc == 0
        )
    for i, cid in kept.items():
        assert container_id(host, f"isaac-sim-{i}") == cid, f"instance {i} was restarted by a scale-down"


def test_scale_back_to_4_starts_warm_and_leaves_the_others_running(host):
    kept = {i: container_id(host, f"isaac-sim-{i}") for i in (0, 1)}
    result = testbed.run_playbook(host, {"isaac_sim_instance_count": INSTANCES})
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr
    testbed.all_ready(host)
    # their configuration did not change, so they were not restarted
    assert {i: container_id(host, f"isaac-sim-{i}") for i in (0, 1)} == kept
    starts = [
        line
        for line in sh(host, "journalctl -u isaac-sim@3 --no-pager").stdout.splitlines()
        if "starting as uid" in line
    ]
    assert "shader cache warm" in starts[-1]
