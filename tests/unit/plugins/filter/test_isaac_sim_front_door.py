"""The isaac_sim_front_door and isaac_sim_password_hash filters."""

from __future__ import annotations

import pytest
from ansible.errors import AnsibleFilterError
from ansible_collections.isaacsim.fleet.plugins.filter import isaac_sim_front_door as fd_filter
from ansible_collections.isaacsim.fleet.plugins.filter import isaac_sim_password_hash as hash_filter
from ansible_collections.isaacsim.fleet.plugins.module_utils.front import door_auth


def settings(**over):
    base = {
        "server_name": "10.0.0.2",
        "port": "443",
        "http_port": "80",
        "auth_port": "9480",
        "api_port": "9481",
        "viewer_port_base": "20000",
        "login_rate": "10r/m",
        "session_hours": 8,
        "users": [{"name": "vic", "role": "viewer", "password_hash": door_auth.hash_password("pw")}],
        "backends": [],
        "cert": "C",
        "key": "K",
        "auth_code": "CODE",
        "store_code": "STORE",
        "api_code": "API",
        "pool_code": "POOL",
    }
    base.update(over)
    return base


def by_name(services):
    return {s["name"]: s for s in services}


def test_errors_services_and_a_refusal_of_bad_settings():
    assert fd_filter.isaac_sim_front_door(settings(), "errors") == []
    # the login service, nginx, and the relay (off here: stopped and removed)
    services = fd_filter.isaac_sim_front_door(settings(), "services")
    assert [(s["name"], s["state"]) for s in services] == [
        ("isaac-sim-front-door-auth.service", "started"),
        ("isaac-sim-front-door-api.service", "started"),
        ("isaac-sim-front-door.service", "started"),
        ("isaac-sim-front-door-turn.service", "absent"),
    ]
    with pytest.raises(AnsibleFilterError, match="front_door_users: empty"):
        fd_filter.isaac_sim_front_door(settings(users=[]), "services")
    # what goes with each unit: its unit file; the scripts, the store of sessions and tokens (never each
    # person's files beside it), the configuration, the sessions' figures where they were written
    removal = by_name(fd_filter.isaac_sim_front_door({"metrics_dir": "/var/lib/node-exporter"}, "removal"))
    assert all(s["state"] == "absent" for s in removal.values())
    assert removal["isaac-sim-front-door-auth.service"]["files"] == {
        "/etc/systemd/system/isaac-sim-front-door-auth.service": {"content": ""}
    }
    assert removal["isaac-sim-front-door-auth.service"]["remove"] == [
        "/usr/local/libexec/isaac-sim/isaac-sim-front-door-auth",
        "/usr/local/libexec/isaac-sim/isaac_sim_door_store.py",
        *(f"/var/lib/isaac-sim-front-door/door.db{end}" for end in ("", "-wal", "-shm", "-journal")),
    ]
    assert removal["isaac-sim-front-door-api.service"]["remove"][-1] == "/var/lib/node-exporter/isaac_sim_sessions.prom"
    assert removal["isaac-sim-front-door.service"]["remove"] == ["/etc/isaac-sim/front-door"]
    # together they remove every file the units were given, or the directory that holds it
    gone = [path for unit in removal.values() for path in list(unit["files"]) + unit["remove"]]
    relayed = settings(turn=True, turn_port="5349", turn_min_port="50000", turn_max_port="50199", turn_gid=107)
    given = [
        path
        for service in fd_filter.isaac_sim_front_door(dict(relayed, turn_secret="S"), "services")
        for path in service["files"]
    ]
    assert "/etc/isaac-sim/front-door/turnserver.conf" in given
    assert all(any(path == g or path.startswith(g + "/") for g in gone) for path in given)
    # the relay off while the front door stays: its files go, the rest stays
    turn_off = by_name(services)["isaac-sim-front-door-turn.service"]
    assert "/etc/isaac-sim/front-door/turn.secret" in turn_off["remove"]
    assert "/etc/isaac-sim/front-door" not in turn_off["remove"]
    with pytest.raises(AnsibleFilterError, match="is not errors, services, removal or end_sessions"):
        fd_filter.isaac_sim_front_door(settings(), "other")
    assert "isaac_sim_front_door" in fd_filter.FilterModule().filters()


def test_the_password_hash_filter_makes_what_the_service_reads():
    made = hash_filter.isaac_sim_password_hash("s3cret")
    assert door_auth.hash_error(made) is None and door_auth.verify_password("s3cret", made)
    with pytest.raises(AnsibleFilterError, match="non-empty string"):
        hash_filter.isaac_sim_password_hash("")
    with pytest.raises(AnsibleFilterError, match="below 10000"):
        hash_filter.isaac_sim_password_hash("x", 100)
    assert "isaac_sim_password_hash" in hash_filter.FilterModule().filters()


def test_a_removal_first_ends_the_sessions_with_the_api_s_own_code_serving_nothing():
    ending = fd_filter.isaac_sim_front_door({"wait": 45}, "end_sessions")
    assert ending["unit"] == "isaac-sim-front-door-api.service"
    assert ending["store"] == "/var/lib/isaac-sim-front-door/door.db"
    argv = ending["argv"]
    assert argv[:2] == ["/usr/bin/python3", "/usr/local/libexec/isaac-sim/isaac-sim-front-door-api"]
    assert argv[argv.index("--end-sessions") + 1] == "the front door was removed"
    assert argv[argv.index("--wait") + 1] == "45" and "--port" not in argv
    assert argv[argv.index("--store") + 1] == ending["store"]
