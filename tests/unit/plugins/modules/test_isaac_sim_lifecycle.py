"""The isaac_sim_lifecycle module end to end, on the lifecycle's scripted host (systemctl,
journalctl and docker as a real host answers them, files in memory), with a plan built by the
plan itself and the instances' directories under a temporary data root."""

from __future__ import annotations

import json
import os

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import layout
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import firewall, lifecycle, plan, runlock
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_lifecycle
from ansible_collections.isaacsim.fleet.tests.unit.helpers import plan_config, run_module
from ansible_collections.isaacsim.fleet.tests.unit.plugins.module_utils.instance.test_lifecycle import (
    OLD,
    READS,
    ScriptedHost,
)

SCRIPTS = {name: f"#!/bin/sh\n# {name}\n" for name in (*layout.SCRIPTS, *layout.POLICY_LIB)}
UNIT_TEMPLATE = os.path.join(layout.UNIT_DIR, layout.UNIT_TEMPLATE)


def a_plan(tmp_path, **over) -> dict:
    """Four 6.x instances without GPUs, their directories under tmp_path owned by this user."""
    cfg = plan_config(data_root=str(tmp_path / "data"), image="reg/isaac-sim:6.0.1")
    cfg.update(over)
    built = plan.build(cfg, {"memory_bytes": 0, "gpu_count": 0, "gpus": [], "ports_held": []})
    built.update(uid=os.getuid(), gid=os.getgid())
    return built


@pytest.fixture()
def host(monkeypatch):
    """Binds the module to a scripted host: call it with the host to use."""
    chosen = {}
    monkeypatch.setattr(lifecycle, "bind", lambda module: chosen["host"].host)

    def use(scripted):
        chosen["host"] = scripted
        return scripted

    return use


def changes(h: ScriptedHost) -> list:
    """What the module did to the host beyond reading it."""
    return [line for line in h.log if not line.startswith(READS + ("journalctl", "docker image inspect"))]


def test_a_fresh_host_gets_its_files_directories_and_instances(host, tmp_path, capsys):
    h = host(ScriptedHost(4, running=False))
    planned = a_plan(tmp_path)
    result = run_module(isaac_sim_lifecycle.main, {"plan": planned, "scripts": SCRIPTS, "image_id": "sha256:a"}, capsys)
    assert result["changed"] is True and result["failed_instance"] is None and result["untouched"] == []
    assert [(d["id"], d["action"]) for d in result["done"]] == [(i, "start") for i in range(4)]
    assert result["plan"]["start"] == [0, 1, 2, 3] and result["network"] is None and result["deferred"] is False
    # the firewall's rules are loaded before any instance opens a port
    assert h.commands("start") == [
        f"systemctl start {firewall.UNIT}",
        "systemctl start " + " ".join(layout.unit(i) for i in range(4)),
    ]
    text, mode = h.files[layout.env_file(2)]
    assert mode == 0o644 and layout.parse(text)[layout.K_IMAGE_ID] == "sha256:a"
    assert h.files[os.path.join(layout.LIBEXEC_DIR, "isaac-sim-run")] == (SCRIPTS["isaac-sim-run"], 0o755)
    roots = [inst["root"] for inst in planned["instances"]]
    assert set(roots) <= set(result["directories"]) and all(os.path.isdir(r) for r in roots)
    assert "diff" not in result
    # the second call finds everything as it should be
    again = run_module(isaac_sim_lifecycle.main, {"plan": planned, "scripts": SCRIPTS, "image_id": "sha256:a"}, capsys)
    assert again["changed"] is False and again["done"] == [] and again["directories"] == []


def test_check_mode_reports_the_changes_and_makes_none(host, tmp_path, capsys):
    h = host(ScriptedHost(4, running=False))
    planned = a_plan(tmp_path)
    args = {"plan": planned, "scripts": SCRIPTS, "_ansible_check_mode": True, "_ansible_diff": True}
    result = run_module(isaac_sim_lifecycle.main, args, capsys)
    assert result["changed"] is True and result["done"] == [] and result["plan"]["start"] == [0, 1, 2, 3]
    assert h.files == {} and changes(h) == [] and not os.path.exists(tmp_path / "data")
    # the diff shows the shared files, never an env file (it may hold secrets)
    shown = {d["after_header"]: d for d in result["diff"]}
    assert shown[UNIT_TEMPLATE]["before"] == "" and "isaac-sim-run" in shown[UNIT_TEMPLATE]["after"]
    assert not any(path.startswith(layout.CONFIG_DIR) for path in shown)


def test_a_missing_script_is_refused_before_any_change(host, tmp_path, capsys):
    h = host(ScriptedHost(2))
    scripts = {k: v for k, v in SCRIPTS.items() if k != "isaac-sim-ports"}
    result = run_module(isaac_sim_lifecycle.main, {"plan": a_plan(tmp_path), "scripts": scripts}, capsys)
    assert result["msg"] == "scripts: isaac-sim-ports is missing. Fix: pass the role's files/isaac-sim-ports."
    assert changes(h) == [] and h.files[layout.env_file(0)][0] == OLD


def test_apply_without_a_plan_is_refused_by_the_argument_spec(host, capsys):
    host(ScriptedHost(1))
    result = run_module(isaac_sim_lifecycle.main, {"action": "apply"}, capsys)
    assert result["msg"] == "action is apply but all of the following are missing: plan"


def test_an_image_that_never_gets_ready_goes_back_and_the_message_says_where_it_is(host, tmp_path, capsys):
    h = host(ScriptedHost(4))
    planned = a_plan(tmp_path, image="reg/isaac-sim:never-ready")
    result = run_module(isaac_sim_lifecycle.main, {"plan": planned, "scripts": SCRIPTS}, capsys)
    assert result["msg"] == (
        "isaac-sim-0: isaac-sim-0 was not ready within 20 s (last lines: loading scene); "
        "it went back to reg/isaac-sim:5.0.0 and is ready again; not reached: isaac-sim-1, isaac-sim-2, isaac-sim-3"
    )
    assert result["failed_instance"]["id"] == 0 and result["failed_instance"]["reverted"] is True
    assert result["untouched"] == [1, 2, 3] and result["changed"] is True
    assert all(h.files[layout.env_file(i)][0] == OLD for i in range(4))


def test_a_day_2_restart_in_check_mode_restarts_nothing(host, capsys):
    h = host(ScriptedHost(3))
    args = {"action": "restart", "ids": [0, 2], "_ansible_check_mode": True}
    result = run_module(isaac_sim_lifecycle.main, args, capsys)
    assert result["changed"] is True and [d["id"] for d in result["done"]] == [0, 2]
    assert changes(h) == []
    done = run_module(isaac_sim_lifecycle.main, {"action": "restart", "ids": [0, 2], "soak_seconds": 2}, capsys)
    assert [d["action"] for d in done["done"]] == ["restart", "restart"] and done["done"][0]["soak_s"] >= 2
    assert h.commands("restart") == [f"systemctl restart {layout.unit(0)}", f"systemctl restart {layout.unit(2)}"]


def test_stop_and_start_move_only_the_instances_named(host, capsys):
    h = host(ScriptedHost(3))
    stopped = run_module(isaac_sim_lifecycle.main, {"action": "stop", "ids": [1]}, capsys)
    assert stopped["changed"] is True and stopped["done"] == [{"id": 1, "action": "stop"}]
    assert h.units[1]["ActiveState"] == "inactive" and h.units[0]["ActiveState"] == "active"
    started = run_module(isaac_sim_lifecycle.main, {"action": "start", "ids": [1]}, capsys)
    assert started["done"] == [{"id": 1, "action": "start"}] and h.units[1]["ActiveState"] == "active"
    checked = run_module(isaac_sim_lifecycle.main, {"action": "stop", "ids": [], "_ansible_check_mode": True}, capsys)
    assert checked["changed"] is False and checked["done"] == []


def test_removing_the_last_instance_forgets_it_and_looks_at_the_network_and_ports(host, capsys):
    h = host(ScriptedHost(1))
    result = run_module(isaac_sim_lifecycle.main, {"action": "remove", "ids": [0]}, capsys)
    assert result["changed"] is True and result["done"] == [{"id": 0, "action": "remove"}]
    assert layout.env_file(0) not in h.files and h.units[0]["UnitFileState"] == "disabled"
    # no Docker to ask: no network; no /proc/sys here: no reserved ports to give back
    assert result["network"] is None and result["reserved_ports"] is False


def test_a_rollout_whose_controller_stopped_renewing_stops_and_records_it(host, tmp_path, monkeypatch, capsys):
    h = host(ScriptedHost(2))
    lock, record = tmp_path / "lock.json", tmp_path / "rollout.json"
    monkeypatch.setattr(runlock, "LOCK", str(lock))
    monkeypatch.setattr(runlock, "RECORD", str(record))
    # renewed an hour before the scripted host's clock
    lock.write_text(json.dumps({"id": "ctl:42:7", "user": "ops", "since": 1, "renewed": h.host.wall() - 3600}))
    args = {"action": "restart", "ids": [0, 1], "controller_run": "ctl:42:7"}
    result = run_module(isaac_sim_lifecycle.main, args, capsys)
    assert result["msg"].startswith("rollout interrupted: its controller stopped renewing its hold on the host ")
    assert result["msg"].endswith("; it stopped before isaac-sim-0, isaac-sim-1, which are as they were")
    assert result["interrupted"] and result["untouched"] == [0, 1] and h.commands("restart") == []
    kept = json.loads(record.read_text())
    assert kept["run"] == "ctl:42:7" and kept["done"] == [] and kept["untouched"] == [0, 1]
    # another run's lock: this call is not the holder, nothing to stop for
    host(ScriptedHost(2))
    other = run_module(isaac_sim_lifecycle.main, dict(args, controller_run="ctl:43:8"), capsys)
    assert not other.get("failed") and [d["id"] for d in other["done"]] == [0, 1]
