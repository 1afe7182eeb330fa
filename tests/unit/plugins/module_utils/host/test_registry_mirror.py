"""The registry mirror (module_utils/host/registry_mirror.py): its checks, files and the references the
fleet pulls through it."""

from __future__ import annotations

import json

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import registry_mirror

GOOD = {
    "upstream": "https://nvcr.io",
    "username": "$oauthtoken",
    "password": "key-123",
    "address": "10.0.0.9",
    "port": 5443,
    "allowed_networks": ["10.0.0.0/16", "fd00::/64"],
    "uid": 104,
    "gid": 110,
}


def test_good_settings_pass():
    assert registry_mirror.check(GOOD) == []
    # ansible-core 2.18 gives set_fact's numbers as text
    assert registry_mirror.check(dict(GOOD, port="5443")) == []


@pytest.mark.parametrize(
    "over, needle",
    [
        ({"upstream": "nvcr.io"}, "registry_mirror_upstream: 'nvcr.io' is not a registry's URL"),
        ({"upstream": "https://nvcr.io/nvidia"}, "registry_mirror_upstream: 'https://nvcr.io/nvidia'"),
        ({"password": ""}, "registry_mirror_password: empty"),
        ({"address": "mirror lab"}, "registry_mirror_address: 'mirror lab' is neither"),
        # what goes into the mirror's configuration and certificate is plain: no line after it, no IPv6 zone
        ({"address": "mirror.lab\n"}, "registry_mirror_address: 'mirror.lab\\n' is neither"),
        ({"address": "fe80::1%eth0"}, "registry_mirror_address: 'fe80::1%eth0' is neither"),
        ({"port": 443}, "registry_mirror_port: 443 is not a port of 1024-65535"),
        ({"upstream": "https://me:secret@nvcr.io"}, "registry_mirror_upstream: holds credentials"),
        ({"allowed_networks": []}, "registry_mirror_allowed_networks: empty"),
        ({"allowed_networks": ["10.0.0.1/16"]}, "registry_mirror_allowed_networks: '10.0.0.1/16' is not a network"),
        ({"allowed_networks": ["everyone"]}, "registry_mirror_allowed_networks: 'everyone' is not a network"),
    ],
)
def test_each_bad_setting_is_named_with_the_fix(over, needle):
    errors = registry_mirror.check(dict(GOOD, **over))
    assert any(e.startswith(needle) and "Fix:" in e for e in errors), errors


def test_the_key_is_in_the_config_alone_which_only_the_registry_s_user_reads():
    files = registry_mirror.files(GOOD, "managed", "CERT", "KEY")
    config = json.loads(files["/etc/isaac-sim/mirror/config.yml"]["content"])
    assert config["proxy"] == {"remoteurl": "https://nvcr.io", "username": "$oauthtoken", "password": "key-123"}
    assert (
        config["http"]["addr"] == ":5443" and config["storage"]["filesystem"]["rootdirectory"] == registry_mirror.DATA
    )
    assert config["http"]["tls"] == {
        "certificate": "/etc/isaac-sim/mirror/mirror.crt",
        "key": "/etc/isaac-sim/mirror/mirror.key",
    }
    assert files["/etc/isaac-sim/mirror/config.yml"] == {
        "content": files["/etc/isaac-sim/mirror/config.yml"]["content"],
        "mode": "0600",
        "uid": 104,
        "gid": 110,
    }
    assert files["/etc/isaac-sim/mirror/mirror.key"] == {"content": "KEY", "mode": "0600", "uid": 104, "gid": 110}
    unit = files["/etc/systemd/system/isaac-sim-mirror.service"]["content"]
    assert "key-123" not in unit and "key-123" not in files["/etc/isaac-sim/mirror/firewall.nft"]["content"]
    assert "User=docker-registry" in unit and "ReadWritePaths=/var/lib/docker-registry" in unit
    assert "ExecStart=/usr/bin/docker-registry serve /etc/isaac-sim/mirror/config.yml" in unit
    # the firewall with full privileges before the sandboxed registry, deleted after it
    assert "ExecStartPre=+/usr/sbin/nft -f /etc/isaac-sim/mirror/firewall.nft" in unit
    assert "ExecStopPost=+-/usr/sbin/nft delete table inet isaac_sim_mirror" in unit
    assert "CapabilityBoundingSet=" in unit.splitlines()


def test_the_mirror_s_port_answers_the_allowed_networks_only():
    rules = registry_mirror.rules(GOOD, "managed")
    assert "table inet isaac_sim_mirror\ndelete table inet isaac_sim_mirror\n" in rules
    assert "    tcp dport 5443 ip saddr { 10.0.0.0/16 } accept" in rules
    assert "    tcp dport 5443 ip6 saddr { fd00::/64 } accept" in rules
    assert rules.index("accept\n    tcp dport 5443 drop") > rules.index("ip saddr")


@pytest.mark.parametrize(
    "image, upstream, through",
    [
        ("nvcr.io/nvidia/isaac-sim:6.0.1", "https://nvcr.io", "m.lab:5443/nvidia/isaac-sim:6.0.1"),
        ("nvcr.io/nvidia/isaac-sim:6.0.1", "nvcr.io", "m.lab:5443/nvidia/isaac-sim:6.0.1"),
        (
            "nvcr.io/nvidia/isaac-sim:6.0.1@sha256:" + "a" * 64,
            "https://nvcr.io",
            "m.lab:5443/nvidia/isaac-sim:6.0.1@sha256:" + "a" * 64,
        ),
        ("172.17.0.1:5555/fixtures/sim:5.1.0", "172.17.0.1:5555", "m.lab:5443/fixtures/sim:5.1.0"),
        ("172.17.0.1:5555/fixtures/sim", "http://172.17.0.1:5555", "m.lab:5443/fixtures/sim"),
        ("ubuntu:24.04", "https://registry-1.docker.io", "m.lab:5443/library/ubuntu:24.04"),
        ("ubuntu:24.04", "docker.io", "m.lab:5443/library/ubuntu:24.04"),
        ("reg.lab/isaac-sim:6.0.1", "https://nvcr.io", None),
    ],
)
def test_only_the_upstream_s_images_are_pulled_through_the_mirror(image, upstream, through):
    assert registry_mirror.mirror_reference(image, "m.lab:5443", upstream) == through
