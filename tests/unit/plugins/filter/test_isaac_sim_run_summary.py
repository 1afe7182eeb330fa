"""The isaac_sim_run_summary filter, as roles/experience/tasks/main.yml calls it: the registered
result of the async isaac_sim_experience task | isaac_sim_run_summary, printed by debug."""

from __future__ import annotations

from ansible_collections.isaacsim.fleet.plugins.filter.isaac_sim_run_summary import FilterModule
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import lifecycle
from ansible_collections.isaacsim.fleet.tests.unit.plugins.module_utils.runs.test_runner import (
    INSTANCE_ENV,
    SIM,
    Host,
    experience_params,
    make,
)

HEADER = "service              role          exit restarts  cpu peak  memory peak"


def summary(result: dict) -> list:
    # what register keeps of an async task polled to its end, beside the module's result
    registered = dict(result, ansible_job_id="j123.456", started=1, finished=1, results_file="/root/.ansible_async/j")
    return FilterModule().filters()["isaac_sim_run_summary"](registered)


def test_a_run_on_the_scripted_host_is_its_verdict_and_a_row_per_service_by_name(tmp_path):
    result = make(Host(tmp_path))[0].experience(experience_params(tmp_path))
    assert summary(result) == [
        "pair on h1 (pair-20261124-0000-ab12): PASSED - every orchestrator exited 0 (check) (3.0 s)",
        HEADER,
        "check                orchestrator     0        0        0%       1000 B",
        "robot                service          -        0        0%       1000 B",
    ]


def test_exit_codes_restarts_and_peaks_as_a_person_reads_them():
    result = {
        "run": "pick-20261124-0930-c0ff",
        "host": "gpu-2",
        "experience": "pick",
        "verdict": {"result": "failed", "service": "check", "reason": "check exited with 3", "seconds": 41.27},
        "services": {
            "check": {"orchestrator": True, "started": True, "exit_code": 3, "restarts": 0},
            "robot": {"orchestrator": False, "started": True, "exit_code": None, "restarts": 2},
            "planner": {"orchestrator": False, "started": False, "exit_code": None, "restarts": 0},
            "logger": {"orchestrator": False, "started": True, "exit_code": 137, "restarts": 1},
        },
        "metrics": {
            "check": {"samples": 20, "cpu_peak_percent": 99.6, "memory_peak_bytes": 3 * 1024**3 // 2},
            "robot": {"samples": 21, "cpu_peak_percent": 250.0, "memory_peak_bytes": 200 * 1024**2},
            "logger": {"samples": 2, "cpu_peak_percent": 0.4, "memory_peak_bytes": 2048},
        },
    }
    assert summary(result) == [
        "pick on gpu-2 (pick-20261124-0930-c0ff): FAILED - check exited with 3 (41.3 s)",
        HEADER,
        "check                orchestrator     3        0      100%      1.5 GiB",
        "logger               service        137        1        0%      2.0 KiB",
        # never started (its dependencies never held): no exit code, no samples
        "planner              service      not started        0         -            -",
        "robot                service          -        2      250%    200.0 MiB",
    ]


def test_a_borrowed_instance_that_did_not_come_back_is_said(tmp_path, monkeypatch):
    def give_back(host, i, run, companions=None):
        """The instance's restart through systemd, which ends without it ready."""
        host.remove(layout.lent_marker(i))
        return "not ready within 300 s"

    monkeypatch.setattr(lifecycle, "give_back", give_back)
    host = Host(tmp_path)
    host.files[layout.env_file(0)] = INSTANCE_ENV
    host.files[layout.marker(0)] = ""
    result = make(host)[0].experience(experience_params(tmp_path, compose=SIM, name="sim", instance=0))
    lines = summary(result)
    assert lines[0].startswith("sim on h1 (sim-20261124-0000-ab12): PASSED - ")
    assert lines[-1] == "after the run, isaac-sim@0 did not come back: not ready within 300 s"
