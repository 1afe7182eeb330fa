"""Host services that are not instances (module_utils/host/host_service.py): files and unit in one call."""

from __future__ import annotations

import os

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import host_service

UNIT = "/etc/systemd/system/isaac-sim-status.service"
SCRIPT = "/usr/local/libexec/isaac-sim/isaac-sim-status-server"
RUNNING = {"ActiveState": "active", "UnitFileState": "enabled", "LoadState": "loaded"}
NEW = {"ActiveState": "inactive", "UnitFileState": "", "LoadState": "not-found"}


@pytest.mark.parametrize(
    "show, changed, expected",
    [
        # a fresh host: written, loaded, enabled, started
        (NEW, [UNIT, SCRIPT], ["write", "daemon-reload", "enable", "start"]),
        # nothing to do on a re-run
        (RUNNING, [], []),
        # a changed script restarts the running service, no reload needed
        (RUNNING, [SCRIPT], ["write", "restart"]),
        (RUNNING, [UNIT], ["write", "daemon-reload", "restart"]),
        # stopped by hand: started again, files unchanged
        (dict(RUNNING, ActiveState="failed"), [], ["start"]),
        # a drop-in is read on daemon-reload only, as a unit is
        (RUNNING, ["/etc/systemd/system/isaac-sim@.service.d/hub.conf"], ["write", "daemon-reload", "restart"]),
    ],
)
def test_started(show, changed, expected):
    assert host_service.actions("started", show, changed, []) == expected


@pytest.mark.parametrize(
    "show, expected",
    [
        (NEW, ["directories", "enable", "start"]),
        (RUNNING, ["directories", "restart"]),
        # caught activating: restarted, with its mount there this time
        (dict(RUNNING, ActiveState="activating"), ["directories", "restart"]),
    ],
)
def test_directories_come_first_and_a_running_service_restarts_on_them(show, expected):
    assert host_service.actions("started", show, [], [], directories=True) == expected


def test_absent_stops_and_disables_before_removing():
    assert host_service.actions("absent", RUNNING, [], [UNIT, SCRIPT]) == [
        "stop",
        "reset-failed",
        "disable",
        "remove",
        "daemon-reload",
    ]
    assert host_service.actions("absent", NEW, [], []) == []
    # failed before (or stopped mid-run): its failed state goes with it, or `systemctl --failed` lists it as
    # "not-found failed" after its file went (seen in CI with the metrics oneshot)
    assert host_service.actions("absent", dict(RUNNING, ActiveState="failed"), [], [UNIT]) == [
        "reset-failed",
        "disable",
        "remove",
        "daemon-reload",
    ]
    assert host_service.actions("absent", dict(NEW, ActiveState="failed"), [], []) == ["reset-failed"]


def test_a_timer_going_away_stops_its_service_while_its_files_remain():
    """The metrics timer stopped mid-run of its service: the service would write its file again
    after it was removed (seen in CI), so the service is stopped too, before anything goes."""
    timer = dict(RUNNING, Triggers="isaac-sim-metrics.service")
    prom = "/var/lib/prometheus/node-exporter/isaac_sim.prom"
    assert host_service.actions("absent", timer, [], [prom])[:1] == ["stop"]
    # a timer stopped earlier whose service may still run: stopped all the same
    stopped = dict(timer, ActiveState="inactive", UnitFileState="disabled")
    assert host_service.actions("absent", stopped, [], [prom]) == ["stop", "reset-failed", "remove"]
    # nothing left: nothing to do, a re-run changes nothing
    assert host_service.actions("absent", stopped, [], []) == []


def test_changed_files_compare_content_and_mode(tmp_path):
    same, other, mode, missing = (str(tmp_path / n) for n in ("same", "other", "mode", "missing"))
    for path in (same, other, mode):
        host_service.write_file(path, "x\n", "0644")
    files = {
        same: {"content": "x\n", "mode": "0644"},
        other: {"content": "y\n", "mode": "0644"},
        mode: {"content": "x\n", "mode": "0755"},
        missing: {"content": "x\n", "mode": "0644"},
    }
    assert host_service.changed_files(files, host_service.read_file) == sorted([other, mode, missing])
    host_service.write_file(mode, "x\n", "0755")
    assert os.stat(mode).st_mode & 0o777 == 0o755
    assert host_service.remove(str(tmp_path)) and not os.path.exists(same)


def test_a_file_with_an_owner_of_its_own_is_written_to_it_and_rewritten_when_owned_otherwise(tmp_path):
    """The registry mirror's secrets: 0600 and its own user's (as root here, chown works)."""
    path = str(tmp_path / "config.yml")
    uid, gid = os.getuid() + 4242, os.getgid() + 4242
    want = {path: {"content": "k\n", "mode": "0600", "uid": uid, "gid": gid}}
    host_service.write_file(path, "k\n", "0600")
    assert host_service.changed_files(want, host_service.read_file) == [path]
    host_service.write_file(path, "k\n", "0600", uid, gid)
    assert (os.stat(path).st_uid, os.stat(path).st_gid, os.stat(path).st_mode & 0o777) == (uid, gid, 0o600)
    assert host_service.changed_files(want, host_service.read_file) == []
    assert host_service.wanted_files({"files": want, "remove": [], "directories": []})[path]["uid"] == uid
    with pytest.raises(host_service.ServiceError, match="uid and gid must be numbers"):
        host_service.wanted_files(
            {"files": {path: {"content": "", "uid": "registry"}}, "remove": [], "directories": []}
        )


def test_directories_are_created_or_reowned_and_kept(tmp_path):
    uid, gid = os.getuid(), os.getgid()
    hub = tmp_path / "hub-cache"
    wanted = [{"path": str(hub), "uid": uid, "gid": gid, "mode": "0750"}]
    assert host_service.directories_to_fix(wanted) == wanted
    host_service.fix_directory(wanted[0])
    (hub / "kept").write_text("cache")
    assert host_service.directories_to_fix(wanted) == []
    os.chmod(hub, 0o777)
    assert host_service.directories_to_fix(wanted) == wanted
    host_service.fix_directory(wanted[0])
    assert (hub / "kept").read_text() == "cache" and os.stat(hub).st_mode & 0o777 == 0o750


def test_removing_the_last_drop_in_removes_its_directory_and_no_other(tmp_path):
    ours, theirs = tmp_path / "isaac-sim@.service.d", tmp_path / "docker.service.d"
    for d in (ours, theirs):
        d.mkdir()
        (d / "hub.conf").write_text("[Unit]\n")
    (theirs / "site.conf").write_text("[Unit]\n")
    assert host_service.remove(str(ours / "hub.conf")) and not ours.exists()
    assert host_service.remove(str(theirs / "hub.conf")) and (theirs / "site.conf").exists()


def _service(tmp_path):
    """A host service on real files: a unit, a script and a directory, each as wanted."""
    unit, script, data = tmp_path / "s.service", tmp_path / "bin" / "s", tmp_path / "data"
    files = {
        str(unit): {"content": "[Service]\nExecStart=/bin/true\n"},
        str(script): {"content": "#!/bin/sh\n", "mode": "0755"},
    }
    directories = [{"path": str(data), "uid": os.getuid(), "gid": os.getgid(), "mode": "0750"}]
    for path, want in files.items():
        host_service.write_file(path, want["content"], want.get("mode", "0644"))
    for d in directories:
        host_service.fix_directory(d)
    params = {"name": "s.service", "files": files, "directories": directories, "remove": [], "state": "started"}
    return params, unit, script, data


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        (None, True),
        ("content", False),
        ("mode", False),
        ("missing", False),
        ("inactive", False),
        # starting or reloading: the module leaves it be, as it leaves a running one
        ("activating", True),
        ("reloading", True),
        ("disabled", False),
        ("directory mode", False),
        ("directory missing", False),
        ("owner", False),
        ("not read", False),
        ("absent", False),
    ],
)
def test_in_place_is_the_module_s_own_decision_on_what_the_plan_read(tmp_path, change, expected):
    """The deploy leaves out the module where in_place says so: it must never say so where the module
    would have done something (checked against the module's own check-mode answer on the same files)."""
    params, unit, script, data = _service(tmp_path)
    show = dict(RUNNING)
    if change == "content":
        unit.write_text("[Service]\nExecStart=/bin/false\n")
    elif change == "mode":
        script.chmod(0o644)
    elif change == "missing":
        script.unlink()
    elif change == "inactive":
        show["ActiveState"] = "failed"
    elif change in ("activating", "reloading"):
        show["ActiveState"] = change
    elif change == "disabled":
        show["UnitFileState"] = "disabled"
    elif change == "directory mode":
        data.chmod(0o755)
    elif change == "directory missing":
        data.rmdir()
    elif change == "owner":
        params["files"][str(unit)].update(uid=os.getuid() + 1, gid=os.getgid())
    seen = host_service.seen(list(params["files"]), [d["path"] for d in params["directories"]], show)
    if change == "not read":
        del seen["files"][str(unit)]
    if change == "absent":
        params["state"] = "absent"
    module = host_service.Service(
        params, "/bin/systemctl", lambda argv: (0, "\n".join(f"{k}={v}" for k, v in show.items()), "")
    )
    assert host_service.in_place(params, seen) is expected
    if change not in ("not read", "absent"):
        assert (module.apply(check=True)["actions"] == []) is expected


def test_seen_keeps_digests_not_contents(tmp_path):
    params, unit, _script, _data = _service(tmp_path)
    seen = host_service.seen([str(unit), str(tmp_path / "none")], [str(tmp_path / "nodir")], RUNNING)
    assert seen["files"][str(unit)][0] == host_service.digest(unit.read_text())
    assert "ExecStart" not in str(seen)
    assert seen["files"][str(tmp_path / "none")] is None and seen["directories"][str(tmp_path / "nodir")] is None
    assert (seen["ActiveState"], seen["UnitFileState"]) == ("active", "enabled")
    # nothing read (an older plan, or a plan not asked): never in place
    assert host_service.in_place(params, {}) is False
