"""The isaac_sim_audit module's adapter: the probe action over a real socket of this machine, and the
host action bound to the host's reads (module_utils/host/audit.py is tested on its own)."""

from __future__ import annotations

import socket

from ansible_collections.isaacsim.fleet.plugins.module_utils.host import audit
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_audit
from ansible_collections.isaacsim.fleet.tests.unit.helpers import run_module


def test_probe_reports_an_open_port_outside_the_allowed_networks(capsys):
    with socket.create_server(("127.0.0.1", 0)) as server:
        port = server.getsockname()[1]
        reports = {"h1": {"findings": [], "address": "127.0.0.1", "ports": [
            {"proto": "tcp", "port": port, "address": "", "kind": "signal", "networks": ["10.0.0.0/8"]}]}}  # fmt: skip
        result = run_module(isaac_sim_audit.main, {"action": "probe", "reports": reports, "timeout": 1}, capsys)
    report = result["report"]
    assert result["changed"] is False and report["clean"] is False and report["findings"] == 1
    assert report["hosts"][0]["findings"][0]["what"] == f"h1 tcp/127.0.0.1:{port} (signal)"


def test_host_action_hands_the_key_to_the_audit_and_returns_what_it_found(monkeypatch, capsys):
    seen = {}

    def report(io, key, secret_names):
        seen.update(key=key, names=secret_names, io=io)
        return {"findings": [audit.finding("registry key", "/root/x", "holds the registry key")], "ports": [],
                "address": "10.0.0.5"}  # fmt: skip

    monkeypatch.setattr(audit, "host_report", report)
    result = run_module(isaac_sim_audit.main, {"key": "nvapi-x", "secret_env_names": ["TOKEN"]}, capsys)
    assert seen["key"] == "nvapi-x" and seen["names"] == ["TOKEN"]
    assert isinstance(seen["io"], audit.HostIO) and seen["io"].key_files is audit.key_files
    assert result["findings"][0]["what"] == "/root/x" and "nvapi-x" not in str(result)
