"""The isaac_sim_registry_mirror filter: the mirror role's check and its files."""

from __future__ import annotations

import pytest
from ansible.errors import AnsibleFilterError
from ansible_collections.isaacsim.fleet.plugins.filter.isaac_sim_registry_mirror import (
    FilterModule,
    isaac_sim_registry_mirror,
)

SETTINGS = {
    "upstream": "https://nvcr.io",
    "username": "$oauthtoken",
    "password": "k",
    "address": "10.0.0.9",
    "port": 5443,
    "allowed_networks": ["10.0.0.0/16"],
    "uid": 104,
    "gid": 110,
    "cert": "CERT",
    "key": "KEY",
}


def test_errors_and_files():
    assert isaac_sim_registry_mirror(SETTINGS, "errors") == []
    assert isaac_sim_registry_mirror(dict(SETTINGS, password=""), "errors")[0].startswith("registry_mirror_password")
    files = isaac_sim_registry_mirror(SETTINGS, "files")
    assert sorted(files) == [
        "/etc/isaac-sim/mirror/config.yml",
        "/etc/isaac-sim/mirror/firewall.nft",
        "/etc/isaac-sim/mirror/mirror.crt",
        "/etc/isaac-sim/mirror/mirror.key",
        "/etc/systemd/system/isaac-sim-mirror.service",
    ]
    assert files["/etc/isaac-sim/mirror/mirror.crt"]["content"] == "CERT"
    assert FilterModule().filters()["isaac_sim_registry_mirror"] is isaac_sim_registry_mirror


def test_files_of_bad_settings_and_an_unknown_question_fail():
    with pytest.raises(AnsibleFilterError, match="registry_mirror_allowed_networks: empty"):
        isaac_sim_registry_mirror(dict(SETTINGS, allowed_networks=[]), "files")
    with pytest.raises(AnsibleFilterError, match="is not errors or files"):
        isaac_sim_registry_mirror(SETTINGS, "units")
