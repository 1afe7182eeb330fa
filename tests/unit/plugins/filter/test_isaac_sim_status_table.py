"""The isaac_sim_status_table filter: report | isaac_sim_status_table."""

from __future__ import annotations

from ansible_collections.isaacsim.fleet.plugins.filter.isaac_sim_fleet_report import FilterModule as ReportFilters
from ansible_collections.isaacsim.fleet.plugins.filter.isaac_sim_status_table import FilterModule
from ansible_collections.isaacsim.fleet.tests.unit.helpers import host_result


def test_table_of_a_report():
    report = ReportFilters().filters()["isaac_sim_fleet_report"]({"gpu-node-1": host_result()}, ["gpu-node-1"])
    lines = FilterModule().filters()["isaac_sim_status_table"](report)
    assert lines[0].startswith("HOST")
    assert len(lines) == 1 + 5 + 1 + 1  # header, five instances, why the stopped one is down, summary
