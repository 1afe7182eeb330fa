"""One digest for the fleet (module_utils/instance/image_pin.py): a tag resolved once, through one
host's Docker daemon."""

from __future__ import annotations

import base64
import json

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib.docker_socket import DockerError
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import image_pin

DIGEST = "sha256:" + "ab" * 32


class Docker:
    """Docker's /distribution answer: a descriptor (Docker 20.10's lowercase keys), or an error."""

    def __init__(self, answer=None, error=None):
        self.answer = answer if answer is not None else {"Descriptor": {"digest": DIGEST}, "Platforms": []}
        self.error, self.asked = error, []

    def distribution(self, name, auth=""):
        self.asked.append((name, auth))
        if self.error:
            raise self.error
        return self.answer


@pytest.mark.parametrize(
    "repository, registry",
    [
        ("nvcr.io/nvidia/isaac-sim", "nvcr.io"),
        ("172.17.0.1:5555/fixtures/isaac-sim-standin", "172.17.0.1:5555"),
        ("localhost/isaac-sim", "localhost"),
        ("nvidia/isaac-sim", "docker.io"),
        ("isaac-sim", "docker.io"),
    ],
)
def test_the_registry_is_found_as_docker_finds_it(repository, registry):
    assert image_pin.registry_of(repository) == registry


def test_a_tag_is_pinned_to_the_digest_it_names_now_with_the_credentials_in_the_header_only():
    docker = Docker()
    found = image_pin.resolve(docker, "nvcr.io/nvidia/isaac-sim:6.0.1", "$oauthtoken", "key-123")
    assert found == {
        "image": "nvcr.io/nvidia/isaac-sim:6.0.1",
        "pinned": f"nvcr.io/nvidia/isaac-sim@{DIGEST}",
        "digest": DIGEST,
    }
    (name, auth) = docker.asked[0]
    assert name == "nvcr.io/nvidia/isaac-sim:6.0.1"
    assert json.loads(base64.urlsafe_b64decode(auth)) == {
        "username": "$oauthtoken",
        "password": "key-123",
        "serveraddress": "nvcr.io",
    }
    # older engines name it Digest; without a password nothing is sent
    docker = Docker({"Descriptor": {"Digest": DIGEST}})
    assert image_pin.resolve(docker, "reg.lab:5000/sim:1")["pinned"] == f"reg.lab:5000/sim@{DIGEST}"
    assert docker.asked == [("reg.lab:5000/sim:1", "")]


def test_an_image_named_by_digest_is_pinned_as_written_without_asking():
    docker = Docker(error=DockerError("must not be asked"))
    found = image_pin.resolve(docker, f"nvcr.io/nvidia/isaac-sim:6.0.1@{DIGEST}")
    assert found["pinned"] == f"nvcr.io/nvidia/isaac-sim@{DIGEST}" and docker.asked == []


def test_a_refused_login_names_the_registry_and_the_fix_and_never_the_key():
    error = DockerError('Docker answered 401 to GET /distribution/x: b\'{"message":"unauthorized: key-123"}\'', 401)
    with pytest.raises(image_pin.PinError) as exc:
        image_pin.resolve(Docker(error=error), "nvcr.io/nvidia/isaac-sim:6.0.1", "$oauthtoken", "key-123", "gpu-01")
    text = str(exc.value)
    assert text.startswith(
        "nvcr.io refused the login of user $oauthtoken from gpu-01 when asked which digest "
        "nvcr.io/nvidia/isaac-sim:6.0.1 names"
    )
    assert "isaac_sim_registry_password" in text and "key-123" not in text and "********" in text


def test_a_refusal_docker_passes_on_as_its_own_500_is_a_refused_login():
    """Docker 20.10 answers GET /distribution with 500 and the registry's own word (recorded on
    Debian 12's docker.io against the Bearer stand-in registry, a wrong key)."""
    error = DockerError(
        "Docker answered 500 to GET /distribution/reg.lab:5555/sim:6.0.1/json: "
        'b\'{"message":"Head \\"http://reg.lab:5555/v2/sim/manifests/6.0.1\\": '
        "unauthorized: authentication required\"}'",
        500,
    )
    with pytest.raises(image_pin.PinError) as exc:
        image_pin.resolve(Docker(error=error), "reg.lab:5555/sim:6.0.1", "$oauthtoken", "wrong", "gpu-01")
    assert str(exc.value).startswith("reg.lab:5555 refused the login of user $oauthtoken from gpu-01")


def test_a_registry_out_of_reach_or_a_bad_answer_is_said_with_the_way_out():
    error = DockerError("cannot reach the Docker daemon at /var/run/docker.sock: [Errno 2] No such file")
    with pytest.raises(image_pin.PinError) as exc:
        image_pin.resolve(Docker(error=error), "reg.lab/sim:1")
    assert "could not ask reg.lab which digest reg.lab/sim:1 names" in str(exc.value)
    assert "isaac_sim_image_pin: false" in str(exc.value)
    with pytest.raises(image_pin.PinError) as exc:
        image_pin.resolve(Docker({"Descriptor": {"digest": "md5:00"}}), "reg.lab/sim:1")
    assert str(exc.value).startswith("reg.lab answered without a digest for reg.lab/sim:1")
    with pytest.raises(image_pin.PinError):
        image_pin.resolve(Docker(), "Not An Image")


def test_each_image_of_the_fleet_is_asked_once_and_the_deploy_says_whom_it_moves():
    docker = Docker()
    old = "nvcr.io/nvidia/isaac-sim@sha256:" + "01" * 32
    images = {f"gpu-0{i}": "nvcr.io/nvidia/isaac-sim:6.0.1" for i in (1, 2, 3, 4)}
    configured = {
        "gpu-01": [old],
        "gpu-02": [f"nvcr.io/nvidia/isaac-sim@{DIGEST}"],
        "gpu-03": [],
        "gpu-04": ["nvcr.io/nvidia/isaac-sim:6.0.0"],
    }
    found = image_pin.pin_fleet(docker, images, configured, "$oauthtoken", "k")
    assert len(docker.asked) == 1
    assert found["pinned"] == {h: f"nvcr.io/nvidia/isaac-sim@{DIGEST}" for h in images}
    assert found["digests"] == {"nvcr.io/nvidia/isaac-sim:6.0.1": DIGEST}
    assert found["summary"] == [
        f"nvcr.io/nvidia/isaac-sim:6.0.1 is {DIGEST} now; this deploy moves gpu-01 (from sha256:010101010101), "
        "gpu-04 (from nvcr.io/nvidia/isaac-sim:6.0.0); gpu-02 runs it already; gpu-03 gets it first"
    ]


MOVED = "sha256:" + "cd" * 32


def mirror_pin(answers, offline=False, docker=None):
    """pin_fleet through the mirror m.lab:5443 of nvcr.io; returns (result, what the mirror was asked, docker)."""
    docker = docker or Docker()
    images = {"gpu-01": "nvcr.io/nvidia/isaac-sim:6.0.1", "gpu-02": "reg.lab/other:1"}
    asked = []

    def ask(reference):
        asked.append(reference)
        return {"image": reference, "pinned": reference.split(":6")[0] + f"@{DIGEST}", "digest": DIGEST}

    found = image_pin.pin_fleet(
        docker, images, {}, "$oauthtoken", "k", "gpu-01", "m.lab:5443", "https://nvcr.io", ask=ask,
        upstream_answers=answers, offline=offline,
    )  # fmt: skip
    return found, asked, docker


def test_an_image_of_the_mirror_s_upstream_is_pinned_to_what_the_upstream_itself_names_now():
    # the mirror's host asked the upstream: its digest, on the mirror's reference; the mirror is not asked (its
    # proxy answers a tag from its cache), another registry is asked directly with the credentials
    answers = {"nvcr.io/nvidia/isaac-sim:6.0.1": {"digest": MOVED, "url": "https://nvcr.io"}}
    found, asked, docker = mirror_pin(answers)
    assert asked == [] and docker.asked == [("reg.lab/other:1", docker.asked[0][1])] and docker.asked[0][1]
    assert found["pinned"] == {"gpu-01": f"m.lab:5443/nvidia/isaac-sim@{MOVED}", "gpu-02": f"reg.lab/other@{DIGEST}"}
    # the reports name the image as written
    assert found["summary"][0].startswith(f"nvcr.io/nvidia/isaac-sim:6.0.1 is {MOVED} now")
    # no host of the inventory runs the mirror: the upstream is asked through this host's Docker
    found, asked, docker = mirror_pin(None)
    assert asked == [] and [name for name, _auth in docker.asked] == [
        "nvcr.io/nvidia/isaac-sim:6.0.1",
        "reg.lab/other:1",
    ]
    assert found["pinned"]["gpu-01"] == f"m.lab:5443/nvidia/isaac-sim@{DIGEST}"


def test_a_tag_the_upstream_withdrew_stops_the_deploy_though_the_mirror_still_holds_it():
    answers = {
        "nvcr.io/nvidia/isaac-sim:6.0.1": {
            "cause": "missing",
            "said": "reading manifest 6.0.1 in nvcr.io/nvidia/isaac-sim: manifest unknown",
            "url": "https://nvcr.io",
        }
    }
    with pytest.raises(image_pin.PinError) as exc:
        mirror_pin(answers)
    # skopeo's last words, where the cause is
    assert str(exc.value).startswith(
        "the upstream https://nvcr.io no longer has nvcr.io/nvidia/isaac-sim:6.0.1 (…reading manifest 6.0.1"
    )
    assert "A withdrawn image is not rolled out; nothing was changed." in str(exc.value)
    # isaac_sim_pin_offline does not make a withdrawn tag good
    with pytest.raises(image_pin.PinError):
        mirror_pin(answers, offline=True)
    # asked through Docker (no mirror host): its 404 says the same
    error = DockerError("manifest for nvcr.io/nvidia/isaac-sim:6.0.1 not found: manifest unknown", status=404)
    with pytest.raises(image_pin.PinError) as exc:
        mirror_pin(None, docker=Docker(error=error))
    assert "no longer has nvcr.io/nvidia/isaac-sim:6.0.1" in str(exc.value)


def test_an_upstream_out_of_reach_stops_the_deploy_unless_the_mirror_s_copy_is_asked_for():
    answers = {"nvcr.io/nvidia/isaac-sim:6.0.1": {"cause": "unreachable", "said": "dial tcp: i/o timeout", "url": "u"}}
    with pytest.raises(image_pin.PinError) as exc:
        mirror_pin(answers)
    assert "could not ask the upstream u which digest nvcr.io/nvidia/isaac-sim:6.0.1 names (unreachable" in str(
        exc.value
    )
    assert "isaac_sim_pin_offline: true" in str(exc.value)
    found, asked, _docker = mirror_pin(answers, offline=True)
    assert asked == ["m.lab:5443/nvidia/isaac-sim:6.0.1"]
    assert found["summary"][0].startswith(
        f"nvcr.io/nvidia/isaac-sim:6.0.1 is {DIGEST} now; the upstream u could not be asked (unreachable); "
        f"isaac_sim_pin_offline: the mirror's copy {DIGEST} is used"
    )


class Conn:
    """An HTTPSConnection to the mirror: records the request, answers a recorded one."""

    def __init__(self, status=200, digest=DIGEST, error=None):
        self.status, self.digest, self.error, self.seen = status, digest, error, {}

    def __call__(self, host, context, timeout):
        self.seen.update(host=host, context=context, timeout=timeout)
        return self

    def request(self, method, path, headers):
        if self.error:
            raise self.error
        self.seen.update(method=method, path=path, accept=headers["Accept"])

    def getresponse(self):
        return self

    def getheader(self, name):
        return self.digest if name == "Docker-Content-Digest" else None

    def close(self):
        self.seen["closed"] = True


def test_the_mirror_is_asked_with_a_head_of_the_manifest_never_a_blob(tmp_path):
    conn = Conn()
    pin = image_pin.ask_mirror("m.lab:5443/nvidia/isaac-sim:6.0.1", str(tmp_path), connect=conn)
    assert pin == {
        "image": "m.lab:5443/nvidia/isaac-sim:6.0.1",
        "pinned": f"m.lab:5443/nvidia/isaac-sim@{DIGEST}",
        "digest": DIGEST,
    }
    assert (conn.seen["host"], conn.seen["method"], conn.seen["path"]) == (
        "m.lab:5443",
        "HEAD",
        "/v2/nvidia/isaac-sim/manifests/6.0.1",
    )
    # an index's digest where the image has one, as Docker's own pin
    assert (
        conn.seen["accept"].startswith("application/vnd.docker.distribution.manifest.list.v2+json")
        and conn.seen["closed"]
    )
    assert image_pin.ask_mirror("m.lab:5443/n/x", str(tmp_path), connect=conn)["image"] == "m.lab:5443/n/x"
    assert conn.seen["path"] == "/v2/n/x/manifests/latest"


def test_a_mirror_that_fails_to_answer_names_itself_and_the_fix(tmp_path):
    with pytest.raises(image_pin.PinError, match=r"m.lab:5443 answered HTTP 404 when asked .* image and tag exist"):
        image_pin.ask_mirror("m.lab:5443/n/x:1", str(tmp_path), connect=Conn(status=404))
    with pytest.raises(image_pin.PinError, match="answered HTTP 200 with no digest"):
        image_pin.ask_mirror("m.lab:5443/n/x:1", str(tmp_path), connect=Conn(digest=None))
    with pytest.raises(image_pin.PinError, match="could not ask the registry mirror m.lab:5443 .* refused"):
        image_pin.ask_mirror("m.lab:5443/n/x:1", str(tmp_path), connect=Conn(error=ConnectionRefusedError("refused")))
