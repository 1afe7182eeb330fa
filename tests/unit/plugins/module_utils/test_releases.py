"""The release table is the one place release knowledge lives: what lists releases agrees with it."""

from pathlib import Path

import yaml
from ansible_collections.isaacsim.fleet.plugins.module_utils.releases import RELEASES, healthcheck, release_of_tag

ROOT = Path(__file__).resolve().parents[4]


def test_the_role_documents_exactly_the_releases_of_the_table():
    specs = yaml.safe_load((ROOT / "roles" / "isaac_sim" / "meta" / "argument_specs.yml").read_text())
    text = " ".join(specs["argument_specs"]["main"]["options"]["isaac_sim_release"]["description"])
    named = {r for r in ("2023.1", "4.x", "5.x", "6.x", "7.x", "3.x") if f"C({r})" in text}
    assert named == set(RELEASES)
    assert specs["argument_specs"]["main"]["options"]["isaac_sim_release"]["default"] in RELEASES


def test_every_release_has_what_the_plan_and_the_gates_read():
    for name, profile in RELEASES.items():
        assert {"uid", "gid", "entrypoint", "mounts", "ports", "ready_pattern", "min_driver", "log_dir"} <= set(profile)
        assert profile["health_port"] in profile["ports"], name
        assert release_of_tag(profile["default_tag"]) == name
        assert f"{profile['log_dir']}/Kit/*/*/kit_*.log" in healthcheck(name, 1234)
