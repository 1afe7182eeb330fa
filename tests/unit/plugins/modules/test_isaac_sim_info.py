"""The isaac_sim_info module end to end, with its commands answered from recordings."""

from __future__ import annotations

import json
import os
import sys

import pytest
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_info
from ansible_collections.isaacsim.fleet.tests.unit.helpers import recorded, run_module


@pytest.fixture()
def host(tmp_path, monkeypatch):
    """A host with four configured instances whose systemctl and journalctl (programs first on
    PATH) answer as recorded and keep their argv; no Docker daemon, no nvidia-smi."""
    config = tmp_path / "etc"
    config.mkdir()
    for i in range(4):
        (config / f"instance-{i}.env").write_text(recorded("instance-2.env").replace("49102", str(49100 + i)))
    bin_dir, log = tmp_path / "bin", tmp_path / "commands.jsonl"
    bin_dir.mkdir()
    for name, answer in (("systemctl", "systemctl-show.txt"), ("journalctl", "journal-reverse.jsonl")):
        (tmp_path / answer).write_text(recorded(answer))
        program = bin_dir / name
        program.write_text(
            f"#!{sys.executable}\nimport json, sys\n"
            f"open({str(log)!r}, 'a').write(json.dumps(sys.argv) + '\\n')\n"
            f"sys.stdout.write(open({str(tmp_path / answer)!r}).read())\n"
        )
        program.chmod(0o755)
    monkeypatch.setenv("PATH", f"{bin_dir}:{os.environ['PATH']}")
    args = {
        "config_dir": str(config),
        "run_dir": str(tmp_path / "run"),
        "docker_host": f"unix://{tmp_path}/docker.sock",
        "gpu_source": "none",
        "public_address": "sim-1.example.org",
    }
    return args, log


def commands(log):
    """The argv of each command the module ran, program names without their directory."""
    lines = log.read_text().splitlines() if log.exists() else []
    return [[os.path.basename(argv[0])] + argv[1:] for argv in map(json.loads, lines)]


def test_reads_every_instance_and_reports_what_it_could_not(host, capsys):
    args, log = host
    result = run_module(isaac_sim_info.main, args, capsys)
    ran = commands(log)
    assert result["changed"] is False and result["deployed"] is True
    assert [r["id"] for r in result["instances"]] == [0, 1, 2, 3]
    assert result["instances"][1]["urls"]["signal"] == "sim-1.example.org:49101"
    assert result["docker_available"] is False and "cannot reach the Docker daemon" in result["errors"][0]
    # systemctl, and the last day's events; the first Docker call found no daemon
    assert result["cost"] == {"spawns": 2, "docker_api_calls": 1}
    assert sorted(c[0] for c in ran) == ["journalctl", "systemctl"]
    events = next(c for c in ran if c[0] == "journalctl")
    assert "-t" in events and "isaac-sim-events" in events
    assert "logs" not in result["instances"][0]


def test_log_lines_cost_one_journalctl_through_run_command(host, capsys):
    args, log = host
    result = run_module(isaac_sim_info.main, dict(args, log_lines=2, instances=[3]), capsys)
    assert [r["id"] for r in result["instances"]] == [3]
    assert result["instances"][0]["logs"] == [
        "isaac-sim@3.service: Deactivated successfully.",
        "Stopped isaac-sim@3.service - Isaac Sim instance 3.",
    ]
    assert result["cost"]["spawns"] == 3
    journal = commands(log)[-1]
    assert journal[0] == "journalctl" and "--lines=2" in journal and journal[-2:] == ["-u", "isaac-sim@3.service"]


def test_negative_log_lines_is_refused(host, capsys):
    args, _commands = host
    result = run_module(isaac_sim_info.main, dict(args, log_lines=-1), capsys)
    assert result["failed"] and result["msg"].startswith("log_lines: must be 0 or more")
