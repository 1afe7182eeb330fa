"""The isaac_sim_mirror_info module: one call into mirror_info.collect, changing nothing."""

from __future__ import annotations

from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_mirror_info
from ansible_collections.isaacsim.fleet.tests.unit.helpers import run_module


def test_the_module_answers_the_mirror_s_state_and_changes_nothing(monkeypatch, capsys):
    seen = []

    def collect(run, min_free_gb):
        seen.append((run, min_free_gb))
        return {"healthy": True, "images": 1}

    monkeypatch.setattr(isaac_sim_mirror_info.mirror_info, "collect", collect)
    result = run_module(isaac_sim_mirror_info.main, {"_ansible_check_mode": True}, capsys)
    assert result["changed"] is False and result["mirror"] == {"healthy": True, "images": 1} and len(seen) == 1
    # the floor is the role's default unless status.yml passes registry_mirror_min_free_gb
    assert seen[0][1] == 20
    run_module(isaac_sim_mirror_info.main, {"min_free_gb": 2.5}, capsys)
    assert seen[1][1] == 2.5
