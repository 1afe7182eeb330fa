"""The nvidia_driver_check module, with nvidia-smi answering as recorded on an H100."""

from __future__ import annotations

import pytest
from ansible.module_utils import basic
from ansible_collections.isaacsim.fleet.plugins.modules import nvidia_driver_check
from ansible_collections.isaacsim.fleet.tests.unit.helpers import recorded, run_module


@pytest.fixture()
def smi(monkeypatch):
    answer = {"bin": "/usr/bin/nvidia-smi", "out": recorded("h100-nvidia-smi-query-gpu.csv")}

    def run_command(self, args, **kwargs):
        assert args[0] == "nvidia-smi" and args[1].startswith("--query-gpu=")
        return 0, answer["out"], ""

    monkeypatch.setattr(basic.AnsibleModule, "run_command", run_command)
    monkeypatch.setattr(basic.AnsibleModule, "get_bin_path", lambda self, name, *a, **kw: answer["bin"])
    return answer


def test_a_new_enough_driver_passes(smi, capsys):
    result = run_module(nvidia_driver_check.main, {"release": "5.x"}, capsys)
    assert result["changed"] is False and result["min_version"] == "570.169"
    assert result["gpus"][0]["driver"] == "580.159.04"


def test_an_older_driver_fails_naming_both_versions(smi, capsys):
    result = run_module(nvidia_driver_check.main, {"release": "6.x", "min_version": "590.1"}, capsys)
    assert result["failed"] and "580.159.04 is older than 590.1" in result["msg"]


def test_no_nvidia_smi_fails(smi, capsys):
    smi["bin"] = None
    result = run_module(nvidia_driver_check.main, {}, capsys)
    assert result["failed"] and "No NVIDIA GPU" in result["msg"]
