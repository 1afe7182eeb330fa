"""The isaac_sim_warm_plan filter: each host's probe read from hostvars, in play order."""

from __future__ import annotations

from ansible_collections.isaacsim.fleet.plugins.filter.isaac_sim_warm_plan import FilterModule, isaac_sim_warm_plan


def test_hosts_are_read_in_play_order_and_a_skipped_probe_needs_nothing():
    hostvars = {
        "h1": {"__isaac_sim_warm": {"cold": {"a": [0, 1]}, "held": []}},
        "h2": {"__isaac_sim_warm": {"cold": {"a": [2]}, "held": []}},
        "h3": {"__isaac_sim_warm": {"skipped": True}},
    }
    out = isaac_sim_warm_plan(["h2", "h1", "h3"], hostvars, [])
    assert out["h2"]["warm"] == ["a"] and out["h1"]["copy"] == ["a"]
    assert out["h3"] == {"warm": [], "fetch": [], "copy": []}
    assert isaac_sim_warm_plan(["h1", "h2"], hostvars, ["a"])["h1"] == {"warm": [], "fetch": [], "copy": ["a"]}
    assert FilterModule().filters()["isaac_sim_warm_plan"] is isaac_sim_warm_plan
