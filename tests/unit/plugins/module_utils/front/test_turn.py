"""The front door's TURN relay (module_utils/front/turn.py); its place among the front door's
files is tested in test_front_door.py."""

from __future__ import annotations

from ansible_collections.isaacsim.fleet.plugins.module_utils.front import turn


def test_the_relay_is_named_as_browsers_name_turn_over_tls():
    assert turn.url("fleet.lab", 5349) == "turns:fleet.lab:5349?transport=tcp"
    assert turn.url("[fd00::1]", "443") == "turns:[fd00::1]:443?transport=tcp"


def test_every_peer_is_denied_but_the_instances_once_each():
    assert turn.peers_denied_but(["10.0.0.6", "10.0.0.5", "10.0.0.6"]) == [
        "denied-peer-ip=0.0.0.0-255.255.255.255",
        "denied-peer-ip=::-ffff:ffff:ffff:ffff:ffff:ffff:ffff:ffff",
        "allowed-peer-ip=10.0.0.5",
        "allowed-peer-ip=10.0.0.6",
    ]
    # no instance behind the front door: the relay relays to nobody
    assert all(line.startswith("denied-") for line in turn.peers_denied_but([]))


def test_the_unit_runs_coturn_as_its_own_user_in_a_sandbox():
    unit = turn.unit("/etc/isaac-sim/front-door", "managed")
    assert unit.startswith("# managed\n")
    for line in ("Type=notify", "User=turnserver", "Group=turnserver", "NoNewPrivileges=yes", "ProtectSystem=strict"):
        assert line in unit.splitlines()
    assert "AmbientCapabilities=\n" in unit
