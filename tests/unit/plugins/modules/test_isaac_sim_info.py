"""The isaac_sim_info module end to end, with its commands answered from recordings."""

from __future__ import annotations

import pytest
from ansible.module_utils import basic
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_info
from ansible_collections.isaacsim.fleet.tests.unit.helpers import recorded, run_module


@pytest.fixture()
def host(tmp_path, monkeypatch):
    """A host with four configured instances whose commands answer as recorded; no Docker daemon."""
    config = tmp_path / "etc"
    config.mkdir()
    for i in range(4):
        (config / f"instance-{i}.env").write_text(recorded("instance-2.env").replace("49102", str(49100 + i)))
    commands = []

    def run_command(self, args, **kwargs):
        commands.append(args)
        name = args[0].rsplit("/", 1)[-1]
        if name == "systemctl":
            return 0, recorded("systemctl-show.txt"), ""
        if name == "journalctl":
            return 0, recorded("journal-reverse.jsonl"), ""
        return 127, "", f"{name}: not found"

    monkeypatch.setattr(basic.AnsibleModule, "run_command", run_command)
    monkeypatch.setattr(basic.AnsibleModule, "get_bin_path", lambda self, name, *a, **kw: f"/usr/bin/{name}")
    args = {
        "config_dir": str(config),
        "run_dir": str(tmp_path / "run"),
        "docker_host": f"unix://{tmp_path}/docker.sock",
        "gpu_source": "none",
        "public_address": "sim-1.example.org",
    }
    return args, commands


def test_reads_every_instance_and_reports_what_it_could_not(host, capsys):
    args, commands = host
    result = run_module(isaac_sim_info.main, args, capsys)
    assert result["changed"] is False and result["deployed"] is True
    assert [r["id"] for r in result["instances"]] == [0, 1, 2, 3]
    assert result["instances"][1]["urls"]["signal"] == "sim-1.example.org:49101"
    assert result["docker_available"] is False and "cannot reach the Docker daemon" in result["errors"][0]
    # systemctl, and the last day's events; the first Docker call found no daemon
    assert result["cost"] == {"spawns": 2, "docker_api_calls": 1}
    assert [c[0] for c in commands] == ["/usr/bin/systemctl", "/usr/bin/journalctl"]
    assert "-t" in commands[1] and "isaac-sim-events" in commands[1]
    assert "logs" not in result["instances"][0]


def test_log_lines_cost_one_journalctl_through_run_command(host, capsys):
    args, commands = host
    result = run_module(isaac_sim_info.main, dict(args, log_lines=2, instances=[3]), capsys)
    assert [r["id"] for r in result["instances"]] == [3]
    assert result["instances"][0]["logs"] == [
        "isaac-sim@3.service: Deactivated successfully.",
        "Stopped isaac-sim@3.service - Isaac Sim instance 3.",
    ]
    assert result["cost"]["spawns"] == 3
    journal = commands[-1]
    assert (
        journal[0] == "/usr/bin/journalctl" and "--lines=2" in journal and journal[-2:] == ["-u", "isaac-sim@3.service"]
    )


def test_negative_log_lines_is_refused(host, capsys):
    args, _commands = host
    result = run_module(isaac_sim_info.main, dict(args, log_lines=-1), capsys)
    assert result["failed"] and result["msg"].startswith("log_lines: must be 0 or more")
