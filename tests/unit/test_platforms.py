"""The roles claim only the platforms the tests run on: every role's meta/main.yml lists Debian releases whose
test hosts a molecule scenario runs (molecule/resources/create.yml's image, or a platform's own), and a release
tested only by a scenario that runs some roles (molecule/trixie: the default scenario's converge and its core
checks) is claimed by those roles and no other."""

from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[2]
HOST_IMAGE = "isaacsim-fleet/test-host:"
# every role is tested on bookworm (all the scenarios); trixie runs the deploy of molecule/trixie: Docker and
# the instances (the toolkit role skips a host without a GPU there, so it is not tested on trixie)
ROLES_TESTED_ON = {"trixie": {"docker_engine", "isaac_sim"}}


def codenames_of_test_hosts() -> dict:
    """{Debian release: the scenarios whose hosts run it}; a host image's tag is its release's codename."""
    default = yaml.safe_load((ROOT / "molecule/resources/create.yml").read_text())[0]["vars"]["testbed_image"]
    found = {}
    for path in sorted(ROOT.glob("molecule/*/molecule.yml")):
        for platform in yaml.safe_load(path.read_text()).get("platforms") or []:
            image = platform.get("image", default)
            if image.startswith(HOST_IMAGE):
                found.setdefault(image[len(HOST_IMAGE) :], set()).add(path.parent.name)
    return found


def claims() -> dict:
    out = {}
    for path in sorted(ROOT.glob("roles/*/meta/main.yml")):
        platforms = yaml.safe_load(path.read_text())["galaxy_info"]["platforms"]
        assert [p["name"] for p in platforms] == ["Debian"], f"{path}: claims {platforms}"
        out[path.parent.parent.name] = set(platforms[0]["versions"])
    return out


def test_every_role_claims_bookworm_where_every_scenario_runs():
    tested = codenames_of_test_hosts()
    assert {"default", "fleet", "toolkit", "cluster"} <= tested["bookworm"]
    roles = claims()
    assert len(roles) >= 10
    for role, versions in roles.items():
        assert "bookworm" in versions, role
        assert versions <= set(tested), f"roles/{role}/meta/main.yml claims {versions}, the tests run {set(tested)}"


def test_a_release_tested_by_one_scenario_is_claimed_by_the_roles_it_runs_and_by_no_other():
    tested = codenames_of_test_hosts()
    assert tested.get("trixie") == {"trixie"}
    roles = claims()
    for codename, expected in ROLES_TESTED_ON.items():
        assert {role for role, versions in roles.items() if codename in versions} == expected, codename
