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
        "viewer_port_base": "20000",
        "login_rate": "10r/m",
        "session_hours": 8,
        "users": [{"name": "vic", "role": "viewer", "password_hash": door_auth.hash_password("pw")}],
        "backends": [],
        "cert": "C",
        "key": "K",
        "auth_code": "CODE",
    }
    base.update(over)
    return base


def test_errors_files_and_a_refusal_of_bad_settings():
    assert fd_filter.isaac_sim_front_door(settings(), "errors") == []
    assert sorted(fd_filter.isaac_sim_front_door(settings(), "files")) == sorted(
        ["isaac-sim-front-door.service", "isaac-sim-front-door-auth.service"]
    )
    with pytest.raises(AnsibleFilterError, match="front_door_users: empty"):
        fd_filter.isaac_sim_front_door(settings(users=[]), "files")
    # what goes with each unit: its unit file; the script, the session key, the configuration
    removal = fd_filter.isaac_sim_front_door({}, "removal")
    assert removal["isaac-sim-front-door-auth.service"] == {
        "files": {"/etc/systemd/system/isaac-sim-front-door-auth.service": {"content": ""}},
        "remove": ["/usr/local/libexec/isaac-sim/isaac-sim-front-door-auth", "/var/lib/isaac-sim-front-door"],
    }
    assert removal["isaac-sim-front-door.service"]["remove"] == ["/etc/isaac-sim/front-door"]
    # together they remove every file the units were given, or the directory that holds it
    gone = [path for unit in removal.values() for path in list(unit["files"]) + unit["remove"]]
    given = [path for unit in fd_filter.isaac_sim_front_door(settings(), "files").values() for path in unit]
    assert all(any(path == g or path.startswith(g + "/") for g in gone) for path in given)
    with pytest.raises(AnsibleFilterError, match="is not errors, files or removal"):
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
