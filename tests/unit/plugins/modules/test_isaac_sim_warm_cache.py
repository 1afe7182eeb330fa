"""The isaac_sim_warm_cache module: its parameters into one call of warm_cache.call, its errors said."""

from __future__ import annotations

from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_warm_cache
from ansible_collections.isaacsim.fleet.tests.unit.helpers import run_module

ARGS = {"plan": {"instances": []}, "image_id": "sha256:aa"}


def test_the_module_passes_its_parameters_and_check_mode(monkeypatch, capsys):
    seen = []

    def call(p, check, run):
        seen.append((p["state"], p["key"], check))
        return {"cold": {}, "keys": {}, "held": [], "store": "/s", "changed": False}

    monkeypatch.setattr(isaac_sim_warm_cache.warm_cache, "call", call)
    result = run_module(isaac_sim_warm_cache.main, dict(ARGS, _ansible_check_mode=True), capsys)
    assert result["changed"] is False and seen == [("probe", None, True)]


def test_a_warm_error_fails_the_task_saying_why(monkeypatch, capsys):
    def call(p, check, run):
        raise isaac_sim_warm_cache.warm_cache.WarmError("the warm run ended before its ready line")

    monkeypatch.setattr(isaac_sim_warm_cache.warm_cache, "call", call)
    result = run_module(isaac_sim_warm_cache.main, dict(ARGS, state="warm", key="0123456789abcdef"), capsys)
    assert result["failed"] and "ended before its ready line" in result["msg"]
