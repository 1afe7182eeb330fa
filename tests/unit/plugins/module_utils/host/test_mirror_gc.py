"""The registry mirror's garbage collection (module_utils/host/mirror_gc.py): what is dropped and
kept, on the filesystem driver's layout, and the registry stopped and started around the collector."""

from __future__ import annotations

import json

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import mirror_gc, mirror_seed
from ansible_collections.isaacsim.fleet.tests.unit.plugins.module_utils.host.test_mirror_seed import (
    digest_of,
    push,
    put,
)


def layout(tmp_path):
    """A mirror's data directory: two images of one repository, one of another, an index of two images."""
    v2 = tmp_path / "docker" / "registry" / "v2"
    old = push(v2, "nvidia/isaac-sim", layers=(b"base", b"old"))
    new = push(v2, "nvidia/isaac-sim", layers=(b"base", b"new"))
    other = push(v2, "lib/x", layers=(b"x",))
    amd, arm = push(v2, "multi/m", layers=(b"amd",)), push(v2, "multi/m", layers=(b"arm",))
    index = json.dumps({"schemaVersion": 2, "manifests": [{"digest": amd}, {"digest": arm}]}).encode()
    hexd = digest_of(index).split(":")[1]
    put(v2, f"blobs/sha256/{hexd[:2]}/{hexd}/data", index)
    put(v2, f"repositories/multi/m/_manifests/revisions/sha256/{hexd}/link", digest_of(index).encode())
    for tag, digest in (("6.0.1", old), ("6.0.2", new)):
        put(v2, f"repositories/nvidia/isaac-sim/_manifests/tags/{tag}/current/link", digest.encode())
    return v2, {"old": old, "new": new, "other": other, "amd": amd, "arm": arm, "index": digest_of(index)}


def test_everything_but_the_kept_digests_and_their_index_s_images_is_doomed(tmp_path):
    v2, d = layout(tmp_path)
    collector = mirror_gc.Collector(None, data=str(tmp_path))
    assert len(mirror_seed.manifests(str(v2))) == 6
    assert collector.plan([d["new"], d["index"]]) == sorted([("nvidia/isaac-sim", d["old"]), ("lib/x", d["other"])])
    assert collector.plan([]) == mirror_seed.manifests(str(v2))


def test_a_dropped_image_takes_its_tags_and_leaves_the_rest(tmp_path):
    v2, d = layout(tmp_path)
    collector = mirror_gc.Collector(None, data=str(tmp_path))
    collector.drop([("nvidia/isaac-sim", d["old"])])
    assert ("nvidia/isaac-sim", d["old"]) not in mirror_seed.manifests(str(v2))
    tags = v2 / "repositories" / "nvidia" / "isaac-sim" / "_manifests" / "tags"
    assert sorted(p.name for p in tags.iterdir()) == ["6.0.2"]
    assert collector.plan([d["new"], d["index"], d["other"]]) == []


def test_the_registry_is_stopped_for_the_collector_and_started_again_even_when_it_fails(tmp_path):
    _v2, d = layout(tmp_path)
    calls = []

    def run(argv):
        calls.append(argv)
        return (1, "", "boom") if "garbage-collect" in argv else (0, "", "")

    collector = mirror_gc.Collector(run, data=str(tmp_path), config="/etc/isaac-sim/mirror/config.yml")
    with pytest.raises(mirror_gc.GcError, match="garbage-collect failed: boom"):
        collector.collect([("lib/x", d["other"])])
    assert calls == [
        ["systemctl", "stop", "isaac-sim-mirror.service"],
        ["runuser", "-u", "docker-registry", "--", "/usr/bin/docker-registry", "garbage-collect",
         "/etc/isaac-sim/mirror/config.yml"],
        ["systemctl", "start", "isaac-sim-mirror.service"],
    ]  # fmt: skip
