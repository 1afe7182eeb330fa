"""Filling the registry mirror with the pinned images (module_utils/host/mirror_seed.py): what the
storage lacks (read on the filesystem driver's layout, as skopeo 1.9.3 left it pushing by digest
into Debian's docker-registry 2.8.2), the copy's commands, and that the key's file never outlives it."""

from __future__ import annotations

import base64
import hashlib
import json
import os
from pathlib import Path

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import mirror_seed

MIRROR = "10.0.0.9:5443"


def digest_of(data: bytes) -> str:
    return "sha256:" + hashlib.sha256(data).hexdigest()


def put(store, path: str, data: bytes) -> None:
    target = store / path
    target.parent.mkdir(parents=True, exist_ok=True)
    target.write_bytes(data)


def push(store, name: str, layers=(b"layer-1", b"layer-2"), skip=()) -> str:
    """An image pushed by digest, as the registry lays it out; `skip` leaves parts out."""
    config = b'{"architecture":"amd64"}'
    parts = [config, *layers]
    manifest = json.dumps(
        {
            "schemaVersion": 2,
            "mediaType": "application/vnd.docker.distribution.manifest.v2+json",
            "config": {"digest": digest_of(config), "size": len(config)},
            "layers": [{"digest": digest_of(x), "size": len(x)} for x in layers],
        }
    ).encode()
    for data in parts + [manifest]:
        d = digest_of(data)
        hexd = d.split(":")[1]
        kind = "_manifests/revisions" if data is manifest else "_layers"
        if ("blob", data) not in skip:
            put(store, f"blobs/sha256/{hexd[:2]}/{hexd}/data", data)
        if ("link", data) not in skip:
            put(store, f"repositories/{name}/{kind}/sha256/{hexd}/link", d.encode())
    return digest_of(manifest)


def test_the_references_through_the_mirror_each_once():
    d = "sha256:" + "ab" * 32
    refs = [f"{MIRROR}/nvidia/isaac-sim@{d}", f"{MIRROR}/nvidia/isaac-sim@{d}", f"{MIRROR}/lib/x@{d}"]
    assert mirror_seed.wanted(refs, MIRROR) == [("nvidia/isaac-sim", d), ("lib/x", d)]


@pytest.mark.parametrize(
    "ref", ["nvcr.io/nvidia/isaac-sim@sha256:" + "ab" * 32, f"{MIRROR}/nvidia/isaac-sim:6.0.1", f"{MIRROR}/x@sha256:1"]
)
def test_a_reference_not_pinned_on_the_mirror_is_refused(ref):
    with pytest.raises(mirror_seed.SeedError, match="is not an image pinned on the mirror 10.0.0.9:5443"):
        mirror_seed.wanted([ref], MIRROR)


def test_an_image_held_whole_lacks_nothing_and_each_missing_part_is_named(tmp_path):
    seeder = mirror_seed.Seeder(None, store=str(tmp_path))
    whole = push(tmp_path, "nvidia/isaac-sim")
    assert seeder.lacking([("nvidia/isaac-sim", whole)]) == {}
    # the same blobs are not this repository's until linked to it (the registry serves per repository)
    assert seeder.lacking([("nvidia/other", whole)]) == {("nvidia/other", whole): [f"manifest {whole}"]}
    # (blobs are the store's, shared by its repositories: one store each)
    no_layer = push(tmp_path / "a", "n/a", skip={("blob", b"layer-2")})
    assert mirror_seed.Seeder(None, store=str(tmp_path / "a")).lacking([("n/a", no_layer)]) == {
        ("n/a", no_layer): [f"blob {digest_of(b'layer-2')}"]
    }
    no_link = push(tmp_path / "b", "n/b", skip={("link", b"layer-1")})
    assert mirror_seed.Seeder(None, store=str(tmp_path / "b")).lacking([("n/b", no_link)]) == {
        ("n/b", no_link): [f"blob {digest_of(b'layer-1')}"]
    }


def test_an_index_is_held_only_with_every_image_of_it(tmp_path):
    amd = push(tmp_path, "n/i", layers=(b"amd",))
    arm = push(tmp_path, "n/i", layers=(b"arm",), skip={("blob", b"arm")})
    index = json.dumps({"schemaVersion": 2, "manifests": [{"digest": amd}, {"digest": arm}]}).encode()
    hexd = digest_of(index).split(":")[1]
    put(tmp_path, f"blobs/sha256/{hexd[:2]}/{hexd}/data", index)
    put(tmp_path, f"repositories/n/i/_manifests/revisions/sha256/{hexd}/link", digest_of(index).encode())
    assert mirror_seed.Seeder(None, store=str(tmp_path)).lacking([("n/i", digest_of(index))]) == {
        ("n/i", digest_of(index)): [f"blob {digest_of(b'arm')}"]
    }


def test_the_upstream_and_its_key_come_from_the_mirror_s_config():
    config = json.dumps({"proxy": {"remoteurl": "https://nvcr.io", "username": "$oauthtoken", "password": "k-1"}})
    upstream = mirror_seed.upstream_of(config)
    assert upstream == {"url": "https://nvcr.io", "username": "$oauthtoken", "password": "k-1"}
    auth = json.loads(mirror_seed.auth_file(upstream))["auths"]
    assert list(auth) == ["nvcr.io"] and base64.b64decode(auth["nvcr.io"]["auth"]).decode() == "$oauthtoken:k-1"
    with pytest.raises(mirror_seed.SeedError, match="names no upstream"):
        mirror_seed.upstream_of("{}")


def test_the_copy_is_byte_for_byte_with_tls_to_an_https_upstream_only():
    d = "sha256:" + "ab" * 32
    https = mirror_seed.copy_argv({"url": "https://nvcr.io"}, "nvidia/isaac-sim", d, 40001, "/run/s/auth.json")
    assert https[:4] == ["/usr/bin/skopeo", "copy", "--all", "--preserve-digests"]
    assert "--src-tls-verify=false" not in https and "--dest-tls-verify=false" in https
    assert https[-2:] == [f"docker://nvcr.io/nvidia/isaac-sim@{d}", f"docker://127.0.0.1:40001/nvidia/isaac-sim@{d}"]
    assert https[https.index("--src-authfile") + 1] == "/run/s/auth.json"
    http = mirror_seed.copy_argv({"url": "http://172.17.0.1:5555"}, "n/x", d, 40001, "/a")
    assert "--src-tls-verify=false" in http and http[-2] == f"docker://172.17.0.1:5555/n/x@{d}"


def test_the_writable_registry_is_loopback_only_as_the_registry_s_user_and_sandboxed():
    config = json.loads(mirror_seed.seed_config(40001))
    assert config["http"] == {"addr": "127.0.0.1:40001"} and "proxy" not in config
    assert config["storage"]["filesystem"]["rootdirectory"] == "/var/lib/docker-registry"
    argv = mirror_seed.registry_argv("/run/isaac-sim-seed.x/seed.yml")
    assert argv[:2] == ["systemd-run", "--unit=isaac-sim-mirror-seed.service"]
    assert argv[-3:] == ["/usr/bin/docker-registry", "serve", "/run/isaac-sim-seed.x/seed.yml"]
    for prop in ("User=docker-registry", "ProtectSystem=strict", "ReadWritePaths=/var/lib/docker-registry"):
        assert f"--property={prop}" in argv
    assert "--property=IPAddressDeny=any" in argv and "--property=IPAddressAllow=localhost" in argv


def test_a_copy_runs_the_registry_then_skopeo_and_leaves_no_key_behind_even_when_it_fails(tmp_path, monkeypatch):
    config = tmp_path / "config.yml"
    config.write_text(json.dumps({"proxy": {"remoteurl": "https://nvcr.io", "username": "u", "password": "k-1"}}))
    scratch = tmp_path / "run"
    scratch.mkdir()
    (scratch / "isaac-sim-seed.left").mkdir()  # a killed run's
    (scratch / "other").mkdir()
    monkeypatch.setattr(mirror_seed.Seeder, "_wait", lambda self, port, timeout: None)
    calls, seen = [], {}

    def run(argv):
        calls.append(argv)
        if argv[0] == "/usr/bin/skopeo":
            authfile = argv[argv.index("--src-authfile") + 1]
            seen["auth"] = (oct(os.stat(authfile).st_mode & 0o777), Path(authfile).read_text())
            return (1, "", "unauthorized: k-1 refused") if "bad" in argv[-1] else (0, "", "")
        return 0, "", ""

    seeder = mirror_seed.Seeder(run, store=str(tmp_path), config=str(config), scratch=str(scratch))
    d = "sha256:" + "ab" * 32
    seeder.copy([("n/x", d)], os.getuid(), os.getgid())
    assert [c[0] for c in calls] == ["systemctl", "systemd-run", "/usr/bin/skopeo", "systemctl"]
    assert calls[-1] == ["systemctl", "stop", "isaac-sim-mirror-seed.service"]
    assert seen["auth"][0] == "0o600" and "nvcr.io" in seen["auth"][1]
    assert sorted(os.listdir(scratch)) == ["other"]
    with pytest.raises(mirror_seed.SeedError) as failed:
        seeder.copy([("n/bad", d)], os.getuid(), os.getgid())
    assert "copying n/bad@" in str(failed.value) and "k-1" not in str(failed.value) and "********" in str(failed.value)
    assert sorted(os.listdir(scratch)) == ["other"] and calls[-1][0] == "systemctl"


def test_a_mirror_host_without_the_mirror_says_which_role_to_run(tmp_path):
    seeder = mirror_seed.Seeder(lambda argv: (0, "", ""), config=str(tmp_path / "none.yml"), scratch=str(tmp_path))
    with pytest.raises(mirror_seed.SeedError, match="this host runs no mirror. Fix: run the registry_mirror role"):
        seeder.copy([("n/x", "sha256:" + "ab" * 32)], 0, 0)


@pytest.mark.parametrize(
    "said, cause, fix",
    [
        ("writing blob: write /var/lib/docker-registry/...: no space left on device", "the mirror's disk is full",
         "registry_mirror_gc.yml"),
        ("reading manifest: unauthorized: authentication required", "refused the mirror's login",
         "registry_mirror_password"),
        ("reading manifest sha256:ab in nvcr.io/x: manifest unknown", "does not have it", "withdrawn tag"),
        ("dial tcp 10.0.0.9:443: connect: connection refused", "does not reach https://nvcr.io", "DNS and proxy"),
        ("something else entirely", "failed: something else entirely", "read skopeo's words"),
    ],
)  # fmt: skip
def test_a_failed_copy_says_where_the_real_cause_and_its_fix(said, cause, fix):
    text = mirror_seed.failure("the registry mirror on m1 (isaac-sim-mirror.service)", "n/x", "sha256:ab",
                               "https://nvcr.io", said, free_bytes=0)  # fmt: skip
    assert text.startswith("the registry mirror on m1 (isaac-sim-mirror.service): copying n/x@sha256:ab from ")
    assert cause in text and fix in text
    # a full disk never reads as a login problem, as it did
    assert ("registry_mirror_password" in text) == (fix == "registry_mirror_password")


def test_a_copy_the_full_disk_cut_short_removes_its_partial_upload_and_says_so(tmp_path, monkeypatch):
    config = tmp_path / "config.yml"
    config.write_text(json.dumps({"proxy": {"remoteurl": "https://nvcr.io", "username": "u", "password": "k-1"}}))
    scratch = tmp_path / "run"
    scratch.mkdir()
    store = tmp_path / "v2"
    uploads = store / "repositories" / "n" / "x" / "_uploads"
    older = uploads / "older-writer"
    older.mkdir(parents=True)
    os.utime(older, (1, 1))  # another writer's, from long before
    monkeypatch.setattr(mirror_seed.Seeder, "_wait", lambda self, port, timeout: None)

    def run(argv):
        if argv[0] == "/usr/bin/skopeo":
            partial = uploads / "0b9d-this-copy"
            partial.mkdir()
            (partial / "data").write_bytes(b"x" * 4096)
            return 1, "", "writing blob: copying: write .../data: no space left on device"
        return 0, "", ""

    seeder = mirror_seed.Seeder(run, store=str(store), config=str(config), scratch=str(scratch), host="m1")
    with pytest.raises(mirror_seed.SeedError) as failed:
        seeder.copy([("n/x", "sha256:" + "ab" * 32)], os.getuid(), os.getgid())
    said = str(failed.value)
    assert said.startswith("the registry mirror on m1 (isaac-sim-mirror.service): copying n/x@")
    assert "the mirror's disk is full" in said and "GiB free now" in said and "partial upload was removed" in said
    assert sorted(os.listdir(uploads)) == ["older-writer"]


def test_the_upstream_itself_is_asked_for_each_tag_with_the_mirror_s_key_and_a_withdrawn_tag_is_named(tmp_path):
    config = tmp_path / "config.yml"
    config.write_text(
        json.dumps({"proxy": {"remoteurl": "http://172.17.0.1:5555", "username": "u", "password": "k-1"}})
    )
    scratch = tmp_path / "run"
    scratch.mkdir()
    manifest = b'{"schemaVersion": 2, "mediaType": "application/vnd.docker.distribution.manifest.v2+json"}'
    calls = []

    def run_bytes(argv):
        calls.append(argv)
        authfile = argv[argv.index("--authfile") + 1]
        assert oct(os.stat(authfile).st_mode & 0o777) == "0o600"
        if argv[-1].endswith(":gone"):
            return 1, b"", b"FATA[0000] Error parsing image name: reading manifest gone: manifest unknown (k-1)"
        if argv[-1].endswith(":down"):
            return 1, b"", b"pinging container registry: dial tcp 172.17.0.1:5555: connect: connection refused"
        return 0, manifest, b""

    seeder = mirror_seed.Seeder(None, config=str(config), scratch=str(scratch))
    up = "172.17.0.1:5555/fixtures/isaac-sim-standin"
    images = [f"{up}:6.0.1", f"{up}:gone", f"{up}:down", f"{up}@sha256:{'ab' * 32}", "nvcr.io/nvidia/isaac-sim:6.0.1"]
    found = seeder.ask(images, "m.lab:5443", run_bytes)
    # by tag and on the mirror's upstream only (a digest is pinned as written; another registry is not its)
    assert sorted(found) == sorted(images[:3])
    assert found[f"{up}:6.0.1"] == {
        "digest": "sha256:" + hashlib.sha256(manifest).hexdigest(),
        "url": "http://172.17.0.1:5555",
    }
    assert found[f"{up}:gone"]["cause"] == "missing" and "k-1" not in found[f"{up}:gone"]["said"]
    assert found[f"{up}:down"]["cause"] == "unreachable"
    assert calls[0][:3] == ["/usr/bin/skopeo", "inspect", "--raw"] and "--tls-verify=false" in calls[0]
    assert calls[0][-1] == "docker://172.17.0.1:5555/fixtures/isaac-sim-standin:6.0.1"
    # the key's file does not outlive the asking; a host that runs no mirror yet answers nothing
    assert os.listdir(scratch) == []
    assert (
        mirror_seed.Seeder(None, config=str(tmp_path / "none.yml"), scratch=str(scratch)).ask(images, "m", run_bytes)
        == {}
    )
