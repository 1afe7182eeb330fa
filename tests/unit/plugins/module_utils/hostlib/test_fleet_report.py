"""The fleet report, its table and the Prometheus text (module_utils/hostlib/fleet_report.py), over recorded results."""

from __future__ import annotations

import re

from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import fleet_report
from ansible_collections.isaacsim.fleet.tests.unit.helpers import host_result


def test_report_counts_the_fleet_and_marks_unreachable_hosts():
    report = fleet_report.build(
        {"a": host_result(), "b": {"unreachable": True, "msg": "Failed to connect\nmore detail"}}, ["a", "b", "c"]
    )
    s = report["summary"]
    assert (s["hosts"], s["reachable"], s["instances"], s["ready"], s["stray"]) == (3, 1, 5, 3, 1)
    b, c = report["hosts"][1], report["hosts"][2]
    assert not b["reachable"] and b["error"] == "Failed to connect" and "more detail" in b["error_detail"]
    assert not c["reachable"] and "no answer" in c["error"]


def test_table_has_one_aligned_line_per_instance():
    lines = fleet_report.table(fleet_report.build({"gpu-node-1": host_result()}, ["gpu-node-1"]))
    assert lines[0].split() == ["HOST", "INSTANCE", "STATE", "READY", "UPTIME", "RESTARTS", "GPU", "URL"]
    rows = [line.split() for line in lines[1:-1]]
    assert [r[1] for r in rows] == ["0", "1", "2", "3", "3", "9"]
    assert rows[0][2:4] == ["ready", "yes"] and rows[0][-1] == "172.17.0.2:49100"
    assert rows[3][2:4] == ["stopped", "no"]
    # a down instance says why on the line under it, as status.json and the dashboard do
    assert " ".join(rows[4][2:]) == "why: stopped: systemctl stop, isaac-sim.target stopped, or Docker stopped under it"
    assert rows[5][2:4] == ["stray-container", "(stray)"]
    # columns line up: URL starts at the same offset on every line
    assert len({line.index("172.17.0.2") for line in lines[1:4]}) == 1
    assert lines[-1].startswith("1 hosts (1 answered), 5 instances: 4 running, 3 ready")


def test_an_instance_a_test_run_holds_says_so_under_its_line():
    result = host_result()
    result["instances"][1]["lent_to"] = "nightly-7"
    lines = fleet_report.table(fleet_report.build({"gpu-node-1": result}, ["gpu-node-1"]))
    rows = [line.split() for line in lines[1:-1]]
    assert [r[1] for r in rows][:3] == ["0", "1", "1"] and " ".join(rows[2][2:]) == "held by: test run nightly-7"
    # a person's session by its id (the door knows whose)
    result["instances"][1]["lent_to"] = "session-0a1b2c3d4e5f"
    lines = fleet_report.table(fleet_report.build({"gpu-node-1": result}, ["gpu-node-1"]))
    assert " ".join(lines[3].split()[2:]) == "held by: session 0a1b2c3d4e5f"


def test_durations():
    assert [fleet_report.duration(v) for v in (None, 5, 65, 3600 + 300, 2 * 86400 + 7200)] == [
        "-",
        "5s",
        "1m05s",
        "1h05m",
        "2d2h",
    ]


def test_prometheus_text_is_well_formed():
    text = fleet_report.prometheus(host_result())
    sample = re.compile(r'^[a-z_]+\{isaac_sim_instance="[^"]+"(,[a-z_]+="[^"]*")*\} -?\d+$')
    for line in text.splitlines():
        assert line.startswith("# HELP ") or line.startswith("# TYPE ") or sample.match(line), line
    assert 'isaac_sim_up{isaac_sim_instance="0"} 1' in text
    assert 'isaac_sim_up{isaac_sim_instance="3"} 0' in text
    assert 'isaac_sim_ready{isaac_sim_instance="3"} 0' in text
    assert 'isaac_sim_up{isaac_sim_instance="9",stray="true"} 1' in text
    assert "instance=" not in text.replace("isaac_sim_instance=", "")
    # no GPU read: no GPU memory samples rather than zeros
    assert "isaac_sim_gpu_memory_used_bytes{" not in text


def test_prometheus_label_values_are_escaped():
    result = host_result()
    result["instances"][0]["image"] = 'reg/x:"quoted"\\'
    assert 'image="reg/x:\\"quoted\\"\\\\"' in fleet_report.prometheus(result)


def test_table_lists_each_companion_under_its_instance():
    result = host_result()
    result["instances"][1]["companions"] = [
        {
            "name": "viewer",
            "state": "ready",
            "ready": True,
            "configured": True,
            "uptime_s": 65,
            "restarts": 1,
            "ports": [{"proto": "tcp", "port": 8211}],
        },
    ]
    lines = fleet_report.table(fleet_report.build({"gpu-node-1": result}, ["gpu-node-1"]))
    rows = [line.split() for line in lines[1:-1]]
    assert [r[1] for r in rows] == ["0", "1", "1/viewer", "2", "3", "3", "9"]
    assert rows[2] == ["gpu-node-1", "1/viewer", "ready", "yes", "1m05s", "1", "-", "8211/tcp"]


def test_the_table_and_metrics_keep_the_last_days_ends_that_nrestarts_forgets():
    inst = {"restarts": 0, "last_day": {"session_ends": 10, "crashes": 3, "unhealthy_restarts": 0, "docker_away": 1}}
    assert fleet_report.restarts_text(inst) == "0 (24h: 3 crashed, 10 sessions ended)"
    assert fleet_report.restarts_text({"restarts": 2, "last_day": None}) == "2"
    text = fleet_report.prometheus({"instances": [dict(inst, id=3, name="isaac-sim-3")]})
    assert 'isaac_sim_crashes_last_day{isaac_sim_instance="3"} 3' in text
    assert 'isaac_sim_session_ends_last_day{isaac_sim_instance="3"} 10' in text


def _on(result, digest, pinned=None, drift=None):
    """A host's result whose configured instances run `digest` (pinned to `pinned`)."""
    for inst in result["instances"]:
        if inst["configured"]:
            inst.update(image="reg/isaac-sim:6.0.1", digest=digest, pinned=pinned, drift=drift)
    return result


def test_an_instance_off_the_fleet_s_digest_drifts_in_the_report_and_the_table():
    old, new = "sha256:" + "1" * 64, "sha256:" + "2" * 64
    results = {"a": _on(host_result(), new), "b": _on(host_result(), new), "c": _on(host_result(), old)}
    report = fleet_report.build(results, ["a", "b", "c"])
    assert report["summary"]["drift"] == 4
    c = [i for i in report["hosts"][2]["instances"] if i["configured"]]
    assert {i["fleet_drift"] for i in c} == {f"runs {old[:19]} where the fleet runs {new[:19]}"}
    assert not any(i.get("fleet_drift") for h in report["hosts"][:2] for i in h["instances"])
    lines = fleet_report.table(report)
    assert "ready (drift)" in [" ".join(line.split()[2:4]) for line in lines if line.startswith("c ")]
    assert lines[-1].endswith(", 4 on another digest than the fleet's")
    # a host's own answer (its status endpoint) compares nothing: the page compares its hosts
    alone = fleet_report.build({"c": _on(host_result(), old)}, ["c"], compare=False)
    assert alone["summary"]["drift"] == 0 and not any("fleet_drift" in i for i in alone["hosts"][0]["instances"])


def test_an_instance_off_its_own_deploy_s_digest_counts_once():
    old, new = "sha256:" + "1" * 64, "sha256:" + "2" * 64
    result = _on(host_result(), new)
    result["instances"][0]["drift"] = f"runs {old[:19]}, its deploy pinned {new[:19]}"
    report = fleet_report.build({"a": result}, ["a"])
    assert report["summary"]["drift"] == 1


def test_time_to_ready_and_the_caches_it_started_with_reach_the_page_and_the_metrics():
    result = host_result()
    result["instances"][0].update(ready_after_s=247, cache_at_start="cold")
    result["instances"][1].update(ready_after_s=12, cache_at_start=None)
    views = fleet_report.build({"h": result}, ["h"])["hosts"][0]["instances"]
    # instance 2 as recorded (its marker 16 s after its container's start), 3 stopped
    assert [v["ready_in"] for v in views[:4]] == ["4m07s (cold caches)", "12s", "16s", None]
    text = fleet_report.prometheus(result)
    assert 'isaac_sim_ready_seconds{isaac_sim_instance="0",cache="cold"} 247' in text
    assert 'isaac_sim_ready_seconds{isaac_sim_instance="1",cache="unknown"} 12' in text
    assert 'isaac_sim_ready_seconds{isaac_sim_instance="3"' not in text


def test_the_registry_mirror_is_reported_serving_or_down_with_what_its_storage_holds():
    serving = {
        "mirror": {
            "healthy": True,
            "active": "active",
            "http_status": 200,
            "repositories": {"nvidia/isaac-sim": 2, "lib/x": 1},
            "images": 3,
            "used_bytes": 3 * 1024**3 + 300 * 1024**2,
            "free_bytes": 40 * 1024**3,
            "size_bytes": 250 * 1024**3,
            "errors": [],
        }
    }
    down = {"mirror": dict(serving["mirror"], healthy=False, active="failed", http_status=None)}
    down["mirror"]["errors"] = ["isaac-sim-mirror.service is failed", "the registry did not answer on port 5443"]
    report = fleet_report.build(
        {"a": host_result()}, ["a"], mirrors={"m1": serving, "m2": down, "m3": {"unreachable": True, "msg": "ssh"}}
    )
    assert [m["host"] for m in report["mirrors"]] == ["m1", "m2", "m3"]
    lines = fleet_report.table(report)[-3:]
    assert lines[0] == (
        "mirror m1: serving (HTTP 200), 3.3 GiB held (3 images in 2 repositories), 40.0 GiB free of 250.0 GiB"
    )
    assert lines[1].startswith("mirror m2: DOWN (no answer), 3.3 GiB held") and lines[1].endswith(
        ": isaac-sim-mirror.service is failed; the registry did not answer on port 5443"
    )
    assert lines[2] == "mirror m3: UNREACHABLE: ssh" and report["mirrors"][2]["healthy"] is False
    # without mirrors the report has no such key, and the table no such line
    assert "mirrors" not in fleet_report.build({"a": host_result()}, ["a"])


def test_each_front_door_gets_a_line_and_each_instance_behind_it_its_entrance():
    said = {
        "url": "https://door.lab/",
        "certificate": {"not_after": "2027-01-10T12:00:00Z"},
        "relay": {"url": "turns:door.lab:5349?transport=tcp", "ports": "50000-50199"},
        "entrances": {"a": {"1": "https://door.lab/viewers/a/1/"}},
    }
    doors = {
        "door": {"door": said, "relay": "active"},
        "old": {"door": dict(said, certificate={"not_after": "2027-01-05T00:00:00Z"}), "relay": "failed"},
        "gone": {"door": None, "relay": "unknown", "error": "file not found"},
    }
    report = fleet_report.build({"a": host_result()}, ["a"], "2026-12-27 12:00:00 UTC", front_doors=doors)
    door, gone, old = report["front_doors"]
    assert (door["certificate_days_left"], door["relay"], door["healthy"]) == (14, "active", True)
    assert door["text"] == (
        "https://door.lab/, certificate until 2027-01-10T12:00:00Z (14 days), relay active "
        "(turns:door.lab:5349?transport=tcp, relay ports 50000-50199)"
    )
    # ending within 14 days, or its relay down: marked, with what to do
    assert old["healthy"] is False and "(8 days), relay failed" in old["text"] and "expires soon. Fix:" in old["text"]
    assert gone["healthy"] is False and gone["text"].startswith("UNREADABLE: file not found. Fix: run playbooks/")
    by_id = {i["id"]: i.get("entrance") for i in report["hosts"][0]["instances"]}
    assert by_id[1] == "https://door.lab/viewers/a/1/" and by_id[0] is None
    lines = fleet_report.table(report)
    assert lines[-3] == "front door door: " + door["text"]
    assert any(line.endswith("https://door.lab/viewers/a/1/ (direct: 172.17.0.2:49101)") for line in lines), lines
    # a door without a relay, and a report time that is not the playbook's: no days, relay off, healthy
    plain = fleet_report.door_view("d", {"door": dict(said, relay=None)}, "now")
    assert plain["healthy"] and plain["certificate_days_left"] is None and plain["text"].endswith(", relay off")
    assert "front_doors" not in fleet_report.build({"a": host_result()}, ["a"])
