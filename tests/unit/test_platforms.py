"""The roles claim only the platforms the tests run on: every role's meta/main.yml lists Debian with only the
releases of the molecule scenarios. test hosts (molecule/resources/create.yml's image and any scenario's own),
so a platform claimed without a test host fails here."""

from pathlib import Path

import yaml

ROOT = Path(__file__).resolve().parents[2]
HOST_IMAGE = "isaacsim-fleet/test-host:"


def codenames_of_test_hosts() -> set:
    """The Debian releases of every test host: the image tag is the release's codename."""
    images = [yaml.safe_load((ROOT / "molecule/resources/create.yml").read_text())[0]["vars"]["testbed_image"]]
    for path in sorted(ROOT.glob("molecule/*/molecule.yml")):
        for platform in yaml.safe_load(path.read_text()).get("platforms") or []:
            images += [v for k, v in platform.items() if k.endswith("image") and isinstance(v, str)]
    hosts = [image for image in images if image.startswith(HOST_IMAGE)]
    assert hosts, images
    return {image[len(HOST_IMAGE) :] for image in hosts}


def test_every_role_claims_the_tested_debian_releases_and_nothing_else():
    tested = codenames_of_test_hosts()
    assert "bookworm" in tested
    roles = sorted(ROOT.glob("roles/*/meta/main.yml"))
    assert len(roles) >= 10
    for path in roles:
        platforms = yaml.safe_load(path.read_text())["galaxy_info"]["platforms"]
        assert [p["name"] for p in platforms] == ["Debian"], f"{path}: claims {platforms}, tested: Debian {tested}"
        assert set(platforms[0]["versions"]) <= tested, f"{path}: claims {platforms[0]['versions']}, tested {tested}"
        assert "bookworm" in platforms[0]["versions"], path
