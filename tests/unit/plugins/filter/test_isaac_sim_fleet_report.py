"""The isaac_sim_fleet_report filter: results | isaac_sim_fleet_report(targets, generated_at)."""

from __future__ import annotations

from ansible_collections.isaacsim.fleet.plugins.filter.isaac_sim_fleet_report import FilterModule
from ansible_collections.isaacsim.fleet.tests.unit.helpers import host_result


def test_positional_arguments_as_documented():
    report = FilterModule().filters()["isaac_sim_fleet_report"]({"a": host_result()}, ["a", "b"], "2026-11-22 13:36")
    assert report["generated_at"] == "2026-11-22 13:36"
    assert [h["host"] for h in report["hosts"]] == ["a", "b"]
    assert report["summary"]["reachable"] == 1
