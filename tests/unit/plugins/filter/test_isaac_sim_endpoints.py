"""The isaac_sim_endpoints filter, as a playbook calls it: plan | isaac_sim_endpoints(host)."""

from __future__ import annotations

from ansible_collections.isaacsim.fleet.plugins.filter.isaac_sim_endpoints import FilterModule


def test_one_line_per_planned_instance():
    endpoints = FilterModule().filters()["isaac_sim_endpoints"]
    plan = {
        "release": "2023.1",
        "instances": [{"name": "isaac-sim-0", "gpu": 0, "ports": {"http": 8211, "native": 8899}}],
    }
    assert endpoints(plan, "10.0.0.5") == [
        "isaac-sim-0 gpu=0 webrtc_client=http://10.0.0.5:8211/streaming/webrtc-client?server=10.0.0.5 "
        "native=10.0.0.5:8899"
    ]
