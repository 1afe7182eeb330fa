"""isaac_sim_info's logic (module_utils/hostlib/fleet_status.py) on outputs recorded from a test host."""

from __future__ import annotations

import fnmatch
import json
import random

import pytest
from ansible_collections.isaacsim.fleet.plugins.filter.systemd_env_quote import systemd_env_quote
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import fleet_status, gpu_usage
from ansible_collections.isaacsim.fleet.tests.unit.helpers import (
    NOW,
    RecordedDocker,
    build_records,
    containers,
    env,
    no_nvml,
    recorded,
)


def records(**kw):
    return {r["name"]: r for r in build_records(**kw)}


def test_systemctl_show_one_block_per_unit():
    units = fleet_status.parse_systemctl_show(recorded("systemctl-show.txt"))
    assert sorted(units) == [0, 1, 2, 3]
    assert units[0]["ActiveState"] == "active" and units[0]["UnitFileState"] == "enabled"
    assert units[3]["ActiveState"] == "inactive" and units[3]["SubState"] == "dead"


def test_systemctl_show_asks_once_for_configured_and_loaded_units():
    argv = fleet_status.systemctl_show_argv([0, 1, 7])
    assert argv[:2] == ["systemctl", "show"]
    assert "NRestarts" in argv[argv.index("-p") + 1]
    assert argv[5:8] == ["isaac-sim@0.service", "isaac-sim@1.service", "isaac-sim@7.service"]
    # every other loaded instance by patterns that leave the named ones out
    assert argv[8:] == [
        "isaac-sim@[!017]*.service",
        "isaac-sim@0?*.service",
        "isaac-sim@1?*.service",
        "isaac-sim@7?*.service",
        "isaac-sim-?*@*.service",
    ]
    # the companions' units in the same call, by name and by patterns
    argv = fleet_status.systemctl_show_argv([2], [(2, "viewer")])
    assert argv[5:7] == ["isaac-sim@2.service", "isaac-sim-viewer@2.service"]
    assert "isaac-sim-viewer[!@]*@*.service" in argv and "isaac-sim-viewer@[!2]*.service" in argv


UNITS = [f"isaac-sim@{i}.service" for i in (0, 1, 2, 7, 10, 11, 12, 70, 100)] + [
    f"isaac-sim-{name}@{i}.service"
    for name in ("v", "vi", "viewer", "viewer2", "v-x", "w", "a-b", "zz", "vie")
    for i in (0, 1, 2, 10, 12, 100)
]


@pytest.mark.parametrize("seed", range(40))
def test_systemctl_show_names_each_unit_once(seed):
    """Each instance or companion unit is asked for once: by its name when configured, else by
    exactly one pattern (systemctl shows a unit once per argument that names or matches it); the
    host's other units by none."""
    rng = random.Random(seed)
    ids = sorted(rng.sample([0, 1, 2, 7, 10, 11, 70], rng.randint(0, 5)))
    names = ["v", "vi", "viewer", "viewer2", "v-x", "w", "a-b"]
    companions = sorted({(rng.choice([0, 1, 2, 10]), rng.choice(names)) for _n in range(rng.randint(0, 5))})
    asked = fleet_status.systemctl_show_argv(ids, companions)[5:]
    for unit in UNITS + ["isaac-sim-status.service", "isaac-sim.target", "isaac-sim-hub-cache.service"]:
        hits = [a for a in asked if (fnmatch.fnmatchcase(unit, a) if set(a) & set("*?[") else unit == a)]
        assert len(hits) == (1 if "@" in unit else 0), (unit, hits)


def test_containers_carry_digest_state_and_uptime():
    c = containers()
    assert set(c) == {"isaac-sim-0", "isaac-sim-1", "isaac-sim-2", "isaac-sim-9"}
    zero = c["isaac-sim-0"]
    assert zero["state"] == "running" and zero["health"] == "none"
    assert zero["digest"] == "sha256:7ea27426fd569cff89afbef669e8d74092ec644c13e2c8c73cf5a0187506ebdd"
    assert zero["labelled_instance"] == 0
    assert zero["uptime_s"] == NOW - zero["started_at"] > 0


def test_ready_instance_has_urls_ports_and_limits():
    r = records()["isaac-sim-2"]
    assert r["state"] == "ready" and r["ready"] is True and r["configured"] and not r["stray"]
    assert r["ports"] == {"signal": 49102, "stream": 48000, "web_viewer": 8212}
    # the address the instance was deployed with wins over the host default
    assert r["public_address"] == "172.17.0.2"
    # no viewer beside it: the block's web-viewer port is not reported
    assert r["urls"] == {"signal": "172.17.0.2:49102", "stream": "172.17.0.2:48000/udp"}
    with_viewer = records(companion_envs={(2, "viewer"): {"ISAAC_SIM_PORTS": "tcp/8212"}})["isaac-sim-2"]
    assert with_viewer["urls"]["web_viewer"] == "http://172.17.0.2:8212/"
    assert r["limits"] == {"memory": "1g", "shm_size": "256m"}
    assert r["enabled"] and r["restarts"] == 0 and r["release"] == "6.x"
    assert r["active_since"] == int(NOW - (11900.0 - 11695.598676))


def test_public_address_override_applies_to_every_url():
    r = records(address_override="sim-7.example.org")["isaac-sim-0"]
    assert r["urls"]["signal"] == "sim-7.example.org:49100"


def test_an_instance_with_an_address_of_its_own_is_reached_there_whatever_the_override():
    envs = {i: env(i) for i in range(4)}
    envs[1] = dict(envs[1], ISAAC_SIM_ADDRESS="10.0.0.51")
    found = {r["name"]: r for r in build_records(envs=envs, address_override="sim-7.example.org")}
    assert found["isaac-sim-1"]["address"] == "10.0.0.51"
    assert found["isaac-sim-1"]["urls"]["signal"] == "10.0.0.51:49101"
    assert found["isaac-sim-0"]["address"] is None and found["isaac-sim-0"]["urls"]["signal"].startswith("sim-7")


def test_stopped_instance_reports_stopped_and_not_ready():
    r = records()["isaac-sim-3"]
    assert r["state"] == "stopped" and r["ready"] is False and r["container"] is None
    assert r["configured"] and r["enabled"]


def test_stray_container_is_reported():
    r = records()["isaac-sim-9"]
    assert r["stray"] and not r["configured"] and r["id"] == 9 and r["unit"] is None
    assert r["state"] == "stray-container" and r["container"]["state"] == "running"
    assert r["ready"] is False


def test_stray_unit_is_reported_but_a_loaded_inactive_one_is_not():
    units = fleet_status.parse_systemctl_show(recorded("systemctl-show.txt"))
    units[5] = {"Id": "isaac-sim@5.service", "LoadState": "loaded", "ActiveState": "failed", "SubState": "failed"}
    units[6] = {
        "Id": "isaac-sim@6.service",
        "LoadState": "loaded",
        "ActiveState": "inactive",
        "UnitFileState": "disabled",
    }
    r = records(units=units)
    assert r["isaac-sim-5"]["stray"] and r["isaac-sim-5"]["state"] == "failed"
    assert "isaac-sim-6" not in r


def test_not_ready_without_the_marker():
    r = records(markers={})["isaac-sim-0"]
    assert r["ready"] is False and r["state"] == "running"


def test_time_to_ready_is_from_the_container_s_start_to_its_marker_with_the_caches_it_found(tmp_path):
    started = containers()["isaac-sim-2"]["started_at"]
    (tmp_path / "instance-2.cache").write_text("cold\n")
    (tmp_path / "instance-0.cache").write_text("warm\n")
    (tmp_path / "instance-1.cache").write_text("lukewarm\n")
    (tmp_path / "instance-x.cache").write_text("warm\n")
    states = fleet_status.read_cache_states(str(tmp_path))
    assert states == {0: "warm", 2: "cold"}
    r = records(markers={2: started + 47}, cache_states=states)["isaac-sim-2"]
    assert (r["ready_after_s"], r["cache_at_start"]) == (47, "cold")
    # not ready: neither; a marker older than the container (a start the gate did not see) says nothing
    r = records(markers={}, cache_states=states)["isaac-sim-2"]
    assert (r["ready_after_s"], r["cache_at_start"]) == (None, None)
    assert records(markers={2: started - 5}, cache_states=states)["isaac-sim-2"]["ready_after_s"] is None
    # a start before this version wrote no cache state: the time alone
    r = records(markers={2: started + 3})["isaac-sim-2"]
    assert (r["ready_after_s"], r["cache_at_start"]) == (3, None)


@pytest.mark.parametrize(
    "active,sub,expected",
    [
        ("active", "running", "ready"),
        ("activating", "start-post", "starting"),
        ("activating", "auto-restart", "restarting"),
        ("failed", "failed", "failed"),
        ("deactivating", "stop-sigterm", "stopping"),
        ("inactive", "dead", "stopped"),
    ],
)
def test_state_words(active, sub, expected):
    assert fleet_status.state_of({"ActiveState": active, "SubState": sub}, None, True) == expected


@pytest.mark.parametrize(
    "active,result,restarts,status,expected",
    [
        ("active", "success", "0", "0", None),
        # systemd is bringing it back: not down
        ("activating", "exit-code", "2", "1", None),
        # a manual start refused by the start limit
        ("failed", "start-limit-hit", "0", "1", "crash loop: "),
        # an automatic restart refused: systemd keeps the last run's result
        ("failed", "exit-code", "2", "1", "crash loop: "),
        ("failed", "exit-code", "0", "1", "failed (exit-code): read journalctl -u isaac-sim@2.service"),
        # isaac-sim-ports: never restarted, whatever the count
        ("failed", "exit-code", "1", "76", "a port of its block is held"),
        # isaac-sim-policy: a container the container policy refused, never started nor restarted
        ("failed", "exit-code", "0", "77", "the container policy refused the container Docker made"),
        ("inactive", "success", "0", "0", "stopped: "),
    ],
)
def test_why_an_instance_is_down(active, result, restarts, status, expected):
    unit = {"ActiveState": active, "Result": result, "NRestarts": restarts, "ExecMainStatus": status}
    said = fleet_status.down_reason(unit, "isaac-sim@2.service")
    assert said == expected if expected is None or expected.endswith(".service") else said.startswith(expected)


def test_restart_count_comes_from_nrestarts():
    units = fleet_status.parse_systemctl_show(recorded("systemctl-show.txt"))
    units[1] = dict(units[1], NRestarts="3", ActiveState="activating", SubState="auto-restart")
    r = records(units=units)["isaac-sim-1"]
    assert r["restarts"] == 3 and r["state"] == "restarting" and r["ready"] is False


@pytest.mark.parametrize(
    "status,health",
    [
        ("Up 2 minutes (healthy)", "healthy"),
        ("Up 5 seconds (health: starting)", "starting"),
        ("Up 1 hour (unhealthy)", "unhealthy"),
        ("Exited (137) 3 seconds ago", "none"),
    ],
)
def test_health_from_status_text(status, health):
    assert fleet_status.health_of(status) == health


def test_env_file_parser_reads_back_what_the_role_quotes():
    secret = 'a$b"c`d\\e f'
    text = f"X={systemd_env_quote(secret)}\nPLAIN=1\n# comment\n"
    assert fleet_status.parse_env_file(text) == {"X": secret, "PLAIN": "1"}
    assert env(2)["ISAAC_SIM_READY_PATTERN"] == "App is loaded\\."


def test_a_headless_instance_reports_its_profile_and_no_url():
    e = dict(env(1), ISAAC_SIM_PORTS="", ISAAC_SIM_PROFILE="headless")
    r = records(envs={1: e})["isaac-sim-1"]
    assert r["profile"] == "headless" and r["urls"] == {}
    # the block stays the instance's
    assert r["ports"] == {"signal": 49101, "stream": 47999, "web_viewer": 8211}
    streaming = dict(env(1), ISAAC_SIM_PORTS="tcp/49101 udp/47999", ISAAC_SIM_PROFILE="streaming")
    assert list(records(envs={1: streaming})["isaac-sim-1"]["urls"]) == ["signal", "stream"]


def test_the_hub_cache_container_is_a_host_service_never_a_stray():
    raw = [
        {
            "Id": "f" * 64,
            "Names": ["/isaac-sim-hub"],
            "State": "running",
            "Status": "Up 5 minutes",
            "Created": NOW - 300,
            "Image": "hub:2.0.0",
            "ImageID": "sha256:1",
            "Labels": {"org.isaacsim.fleet.host-service": "hub"},
        }
    ]
    hub = fleet_status.parse_containers(raw, [], NOW)
    assert hub["isaac-sim-hub"]["host_service"] == "hub"
    found = records(containers=dict(containers(), **hub))
    assert "isaac-sim-hub" not in found and found.keys() == records().keys()


def test_a_test_run_s_containers_are_listed_as_such_never_as_strays():
    raw = [
        {
            "Id": "e" * 64,
            "Names": ["/isaac-sim-run-pick-20261123-101500-ab12-planner"],
            "State": "running",
            "Status": "Up 5 seconds",
            "Created": NOW - 5,
            "Image": "reg/planner:1",
            "ImageID": "sha256:2",
            "Labels": {
                "org.isaacsim.fleet.run": "pick-20261123-101500-ab12",
                "org.isaacsim.fleet.run-service": "planner",
            },
        }
    ]
    run = fleet_status.parse_containers(raw, [], NOW)
    assert run["isaac-sim-run-pick-20261123-101500-ab12-planner"]["test_service"] == "planner"
    found = records(containers=dict(containers(), **run))
    assert found.keys() == records().keys()


def test_2023_instance_gets_the_browser_client_url():
    e = dict(env(0), ISAAC_SIM_RELEASE="2023.1")
    for k in [k for k in e if k.startswith("ISAAC_SIM_PORT_")]:
        del e[k]
    e.update(ISAAC_SIM_PORT_HTTP="8211", ISAAC_SIM_PORT_WEBRTC="8011", ISAAC_SIM_PORT_NATIVE="48010")
    r = records(envs={0: e})["isaac-sim-0"]
    assert r["urls"]["webrtc_client"] == "http://172.17.0.2:8211/streaming/webrtc-client?server=172.17.0.2"


def test_gpu_memory_is_summed_per_container():
    gpu = gpu_usage.parse_smi_xml(recorded("standin-nvidia-smi-q-x.xml"))
    cid = containers()["isaac-sim-0"]["id"]
    envs = {i: env(i) for i in range(4)}
    envs[0]["ISAAC_SIM_GPU"] = "0"
    r = records(envs=envs, gpu=gpu, pid_containers={4242: cid, 99: cid, 777: None})
    assert r["isaac-sim-0"]["gpu"] == 0
    assert r["isaac-sim-0"]["gpu_memory_used_mib"] == 9120 + 100
    assert {p["pid"] for p in r["isaac-sim-0"]["gpu_processes"]} == {4242, 99}
    assert r["isaac-sim-1"]["gpu_memory_used_mib"] == 0  # GPU read, nothing of its own
    assert records()["isaac-sim-1"]["gpu_memory_used_mib"] is None  # no GPU read at all


def test_journal_tail_keeps_the_last_lines_oldest_first_and_stops_early():
    lines = recorded("journal-reverse.jsonl").splitlines()
    tails = fleet_status.take_journal_tail(iter(lines), [3], 3)
    assert tails[3] == [
        "Error: No such container: isaac-sim-3",
        "isaac-sim@3.service: Deactivated successfully.",
        "Stopped isaac-sim@3.service - Isaac Sim instance 3.",
    ]

    def no_reading_past(limit):
        for n, line in enumerate(lines):
            if n >= limit:
                raise AssertionError("read past the lines it needed")
            yield line

    assert len(fleet_status.take_journal_tail(no_reading_past(2), [3], 2)[3]) == 2


def test_journal_tail_of_a_quiet_unit_is_empty():
    tails = fleet_status.take_journal_tail(iter(recorded("journal-reverse.jsonl").splitlines()), [2, 3], 2)
    assert tails[2] == [] and len(tails[3]) == 2


def test_journal_argv_bounds_the_read_to_the_lines_asked():
    argv = fleet_status.journal_argv([0, 3], 10)
    assert argv[0] == "journalctl" and "--reverse" in argv and "--output=json" in argv
    assert "--lines=10" in argv
    assert argv[-4:] == ["-u", "isaac-sim@0.service", "-u", "isaac-sim@3.service"]


class Journal:
    """journalctl over a list of entries, newest first, honouring --lines and -u."""

    def __init__(self, entries):
        self.entries = entries
        self.reads = []

    def run(self, argv):
        limit = int(next(a for a in argv if a.startswith("--lines="))[len("--lines=") :])
        units = {argv[n + 1] for n, a in enumerate(argv) if a == "-u"}
        self.reads.append((sorted(units), limit))
        found = [e for e in self.entries if units & {e.get(k) for k in ("_SYSTEMD_UNIT", "UNIT", "COREDUMP_UNIT")}]
        return 0, "".join(json.dumps(e) + "\n" for e in found[:limit]), ""


def entry(i, message):
    return {"_SYSTEMD_UNIT": f"isaac-sim@{i}.service", "MESSAGE": message}


def test_journal_is_read_once_when_every_unit_has_its_lines():
    journal = Journal([entry(n % 2, f"line {n}") for n in range(100)])
    tails, error = fleet_status.read_journal_tails(journal.run, [0, 1], 3)
    assert error is None and journal.reads == [([f"isaac-sim@{i}.service" for i in (0, 1)], 6)]
    assert tails == {0: ["line 4", "line 2", "line 0"], 1: ["line 5", "line 3", "line 1"]}


def test_a_chatty_unit_does_not_crowd_out_a_quiet_one():
    # unit 0 wrote 50 lines since unit 1's last two
    journal = Journal([entry(0, f"chatty {n}") for n in range(50)] + [entry(1, "quiet b"), entry(1, "quiet a")])
    tails, error = fleet_status.read_journal_tails(journal.run, [0, 1], 3)
    assert error is None
    assert tails[0] == ["chatty 2", "chatty 1", "chatty 0"]
    assert tails[1] == ["quiet a", "quiet b"]  # all it has
    assert journal.reads == [(["isaac-sim@0.service", "isaac-sim@1.service"], 6), (["isaac-sim@1.service"], 3)]


def test_entries_no_unit_keeps_widen_the_window_until_the_end():
    other = {"COREDUMP_UNIT": "isaac-sim@0.service", "_SYSTEMD_UNIT": "systemd-coredump@1.service", "MESSAGE": "core"}
    journal = Journal([other] * 4 + [entry(0, "last"), entry(0, "first")])
    tails, error = fleet_status.read_journal_tails(journal.run, [0], 2)
    assert error is None and tails[0] == ["first", "last"]
    assert [limit for _units, limit in journal.reads] == [2, 4, 8]


def test_journal_failure_is_reported():
    tails, error = fleet_status.read_journal_tails(lambda argv: (1, "", "Failed to add filter\n"), [0], 5)
    assert tails == {} and error == "journalctl failed: Failed to add filter"


@pytest.mark.parametrize("n", [1, 4, 8])
def test_cost_does_not_grow_with_instances(tmp_path, n):
    config = tmp_path / "etc"
    config.mkdir()
    for i in range(n):
        (config / f"instance-{i}.env").write_text(recorded("instance-2.env"))
    spawned = []

    def run(argv):
        spawned.append(argv[0])
        if argv[0] == "systemctl":
            return 0, recorded("systemctl-show.txt"), ""
        if argv[0] == "journalctl":
            return 0, recorded("journal-reverse.jsonl"), ""
        return 0, recorded("standin-nvidia-smi-q-x.xml"), ""

    docker = RecordedDocker()
    result = fleet_status.gather(
        run, None, docker, no_nvml, config_dir=str(config), run_dir=str(tmp_path / "run"), log_lines=5
    )
    assert len([r for r in result["instances"] if r["configured"]]) == n
    # the journal twice: the last day's events, and the log tails
    assert sorted(spawned) == ["journalctl", "journalctl", "nvidia-smi", "systemctl"]
    assert docker.calls == 2
    assert result["deployed"] and result["summary"]["configured"] == n
    three = next(r for r in result["instances"] if r["id"] == 3)
    assert three["logs"][-1] == "Stopped isaac-sim@3.service - Isaac Sim instance 3."
    # each part of the call timed, in the order it ran
    assert list(result["timings_ms"]) == ["files", "docker", "gpu", "systemd", "build", "events", "logs"]
    assert all(ms >= 0 for ms in result["timings_ms"].values())


def test_each_instance_says_which_test_run_holds_it(tmp_path):
    run_dir = tmp_path / "run"
    (run_dir / "instance-1.lent").mkdir(parents=True)
    (run_dir / "instance-1.lent" / "run").write_text("nightly-7\n4242\n")
    # a marker being made (its file not written yet) still holds the instance
    (run_dir / "instance-2.lent").mkdir()
    (run_dir / "instance-x.lent").mkdir()
    assert fleet_status.read_loans(str(run_dir)) == {1: "nightly-7", 2: "a run"}
    # a session a rollout ends says when and by whom; an unreadable notice says nothing
    (run_dir / "instance-3.lent").mkdir()
    (run_dir / "instance-3.lent" / "run").write_text("session-ab12\n\n")
    (run_dir / "instance-3.lent" / "ending").write_text('{"at": 1795000120.5, "by": "olga"}\n')
    (run_dir / "instance-2.lent" / "ending").write_text("{half")
    endings = {}
    assert fleet_status.read_loans(str(run_dir), endings)[3] == "session-ab12"
    assert endings == {3: {"at": 1795000120.5, "by": "olga"}}
    for marker in ("instance-3.lent/ending", "instance-3.lent/run", "instance-2.lent/ending"):
        (run_dir / marker).unlink()
    (run_dir / "instance-3.lent").rmdir()
    config = tmp_path / "etc"
    config.mkdir()
    for i in range(3):
        (config / f"instance-{i}.env").write_text(recorded("instance-2.env"))
    result = fleet_status.gather(
        lambda argv: (0, "", ""), None, RecordedDocker(), no_nvml, config_dir=str(config), run_dir=str(run_dir),
        gpu_source="none",
    )  # fmt: skip
    held = {r["id"]: r["lent_to"] for r in result["instances"] if r["id"] in (0, 1, 2)}
    assert held == {0: None, 1: "nightly-7", 2: "a run"}


def test_a_host_without_the_collection_is_not_deployed(tmp_path):
    result = fleet_status.gather(
        lambda argv: (0, "", ""),
        None,
        RecordedDocker(),
        no_nvml,
        config_dir=str(tmp_path),
        run_dir=str(tmp_path),
        unit_path=str(tmp_path / "none"),
        gpu_source="none",
    )
    assert result["deployed"] is False
    assert [r["name"] for r in result["instances"]] == ["isaac-sim-0", "isaac-sim-1", "isaac-sim-2", "isaac-sim-9"]
    assert all(r["stray"] for r in result["instances"])


def test_default_ipv4_without_ip_sockets_is_the_loopback(monkeypatch):
    """Where a sandbox allows no IPv4 socket (RestrictAddressFamilies), the exporter still runs."""

    def refused(*_args):
        raise OSError(97, "Address family not supported by protocol")

    monkeypatch.setattr(fleet_status.socket, "socket", refused)
    assert fleet_status.default_ipv4() == "127.0.0.1"


def test_default_ipv4_is_an_address():
    parts = fleet_status.default_ipv4().split(".")
    assert len(parts) == 4 and all(p.isdigit() for p in parts)


def test_companions_show_under_their_instance_never_as_strays():
    text = (
        "Id=isaac-sim-viewer@1.service\nLoadState=loaded\nActiveState=active\nSubState=running\n"
        "UnitFileState=enabled\nNRestarts=2\n\n"
        "Id=isaac-sim-rec@1.service\nLoadState=loaded\nActiveState=failed\nSubState=failed\nUnitFileState=enabled\n"
    )
    units = fleet_status.parse_companion_units(text)
    assert set(units) == {(1, "viewer"), (1, "rec")}
    listed = [
        {
            "Id": "c" * 64,
            "Names": ["/isaac-sim-1-viewer"],
            "State": "running",
            "Status": "Up 5 minutes (healthy)",
            "Created": NOW - 300,
            "Image": "reg/viewer:1",
            "ImageID": "sha256:v",
            "Labels": {"org.isaacsim.fleet.instance": "1", "org.isaacsim.fleet.companion": "viewer"},
        }
    ]
    found = dict(containers(), **fleet_status.parse_containers(listed, [], NOW))
    records = build_records(
        containers=found,
        companion_envs={
            (1, "viewer"): {"ISAAC_SIM_IMAGE": "reg/viewer:1", "ISAAC_SIM_PORTS": "tcp/8211"},
            (1, "rec"): {"ISAAC_SIM_IMAGE": "reg/rec:1", "ISAAC_SIM_PORTS": ""},
        },
        companion_units=units,
        companion_markers={(1, "viewer")},
    )
    assert not any(r["name"] == "isaac-sim-1-viewer" for r in records)
    assert fleet_status.summarize(records)["stray"] == sum(1 for r in build_records() if r["stray"])
    inst = next(r for r in records if r["id"] == 1)
    by_name = {c["name"]: c for c in inst["companions"]}
    viewer, rec = by_name["viewer"], by_name["rec"]
    assert viewer["state"] == "ready" and viewer["health"] == "healthy" and viewer["restarts"] == 2
    assert viewer["unit"] == "isaac-sim-viewer@1.service" and viewer["ports"] == [{"proto": "tcp", "port": 8211}]
    assert viewer["uptime_s"] == 300
    assert rec["state"] == "failed" and not rec["ready"] and rec["configured"]
    assert next(r for r in records if r["id"] == 0)["companions"] == []


def test_the_last_days_session_ends_and_crashes_come_from_the_events_journal():
    text = "\n".join(
        [
            "event=session_end container=isaac-sim-3",
            "event=session_end container=isaac-sim-3",
            "event=crash container=isaac-sim-3",
            "event=crash container=isaac-sim-3",
            "event=unhealthy_restart container=isaac-sim-1",
            "event=docker_away container=isaac-sim-1",
            "event=something_new container=isaac-sim-1",
            "-- No entries --",
        ]
    )
    counts = fleet_status.parse_events(text)
    assert counts["isaac-sim-3"] == {"session_ends": 2, "crashes": 2, "unhealthy_restarts": 0, "docker_away": 0}
    assert counts["isaac-sim-1"] == {"session_ends": 0, "crashes": 0, "unhealthy_restarts": 1, "docker_away": 1}
    assert fleet_status.events_argv()[:3] == ["journalctl", "-t", "isaac-sim-events"]


def test_a_started_command_takes_its_words_literally_and_a_hung_or_missing_one_reads_as_127():
    words = "$(touch /tmp/x); `id` | ; 'a' \"b\" \\n"
    assert fleet_status.start(["printf", "%s", words])() == (0, words, "")
    hung = fleet_status.start(["sleep", "30"], timeout=0.2)
    assert hung.spawned and hung() == (127, "", "sleep did not answer within 0.2 s")
    missing = fleet_status.start(["no-such-program-here"])
    assert not missing.spawned and missing() == (127, "", "no-such-program-here is not installed")


def test_gather_without_run_or_start_says_so_instead_of_recursing():
    with pytest.raises(TypeError, match="needs run or start"):
        fleet_status.gather(None, None, None, None)


def test_drift_is_a_running_instance_off_the_digest_its_deploy_pinned():
    pinned, other = "sha256:" + "a" * 64, "sha256:" + "b" * 64
    assert fleet_status.drift(pinned, [other, pinned], other) is None
    assert fleet_status.drift(pinned, [other], other) == f"runs {other[:19]}, its deploy pinned {pinned[:19]}"
    # not pinned (an older deploy, isaac_sim_image_pin: false), or nothing running: no drift to say
    assert fleet_status.drift(None, [other], other) is None and fleet_status.drift(pinned, [], None) is None
