"""The isaac_sim_image_pin module: one call into image_pin.resolve over the host's Docker socket."""

from __future__ import annotations

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerError
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_image_pin
from ansible_collections.isaacsim.fleet.tests.unit.helpers import run_module

DIGEST = "sha256:" + "cd" * 32


@pytest.fixture()
def docker(monkeypatch):
    seen = {}

    class Socket:
        def __init__(self, path, timeout):
            seen.update(path=path, timeout=timeout)

        def distribution(self, name, auth=""):
            if name.endswith(":gone"):
                raise DockerError("Docker answered 404 to GET /distribution: manifest unknown", 404)
            return {"Descriptor": {"digest": DIGEST}}

    monkeypatch.setattr(isaac_sim_image_pin, "DockerSocket", Socket)
    return seen


def test_the_module_answers_the_pinned_reference_and_changes_nothing(docker, capsys):
    result = run_module(
        isaac_sim_image_pin.main,
        {"images": {"a": "reg.lab:5000/sim:6.0.1"}, "registry_password": "k", "_ansible_check_mode": True},
        capsys,
    )
    assert result["changed"] is False and result["pinned"] == {"a": f"reg.lab:5000/sim@{DIGEST}"}
    assert docker == {"path": "/var/run/docker.sock", "timeout": 60}


def test_the_module_fails_with_the_reason(docker, capsys):
    result = run_module(isaac_sim_image_pin.main, {"images": {"a": "reg.lab:5000/sim:gone"}}, capsys)
    # the registry answered 404: the tag is gone, and the message says so
    assert result["failed"] and result["msg"].startswith("reg.lab:5000 no longer has reg.lab:5000/sim:gone")
