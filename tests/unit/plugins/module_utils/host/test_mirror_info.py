"""The registry mirror's health and storage for status (module_utils/host/mirror_info.py)."""

from __future__ import annotations

import json
import os
import socket

from ansible_collections.isaacsim.fleet.plugins.module_utils.host import mirror_info
from ansible_collections.isaacsim.fleet.plugins.module_utils.hostlib import fleet_report


def storage(tmp_path):
    v2 = tmp_path / "docker" / "registry" / "v2"
    for repo, count in (("nvidia/isaac-sim", 2), ("lib/busybox", 1)):
        for n in range(count):
            link = v2 / "repositories" / repo / "_manifests" / "revisions" / "sha256" / f"{n:064x}" / "link"
            link.parent.mkdir(parents=True)
            link.write_text("sha256:x")
        (v2 / "repositories" / repo / "_layers" / "sha256").mkdir(parents=True)
    blob = v2 / "blobs" / "sha256" / "ab" / ("ab" * 32) / "data"
    blob.parent.mkdir(parents=True)
    blob.write_bytes(b"x" * 5000)
    return v2


def test_what_the_storage_holds_per_repository_and_its_bytes(tmp_path):
    v2 = storage(tmp_path)
    assert mirror_info.held(str(v2)) == {"lib/busybox": 1, "nvidia/isaac-sim": 2}
    assert mirror_info.held(str(tmp_path / "none")) == {}
    assert mirror_info.used_bytes(str(tmp_path)) == 5000 + 3 * len("sha256:x")


def test_the_port_comes_from_the_registry_s_config():
    assert mirror_info.port_of(json.dumps({"http": {"addr": ":5443"}})) == 5443


def test_a_mirror_whose_unit_failed_and_port_is_silent_is_down_with_both_reasons(tmp_path):
    storage(tmp_path)
    with socket.socket() as s:  # a port nothing listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    config = tmp_path / "config.yml"
    config.write_text(json.dumps({"http": {"addr": f":{port}"}}))
    state = mirror_info.collect(lambda argv: (3, "failed\n", ""), data=str(tmp_path), config=str(config))
    assert state["healthy"] is False and state["active"] == "failed" and state["http_status"] is None
    assert state["errors"][0] == "isaac-sim-mirror.service is failed"
    assert state["errors"][1].startswith(f"the registry did not answer on port {port}")
    assert state["images"] == 3 and state["used_bytes"] > 5000 and state["size_bytes"] >= state["free_bytes"] > 0


def test_a_host_without_the_mirror_s_config_says_which_role_to_run(tmp_path):
    state = mirror_info.collect(lambda argv: (3, "inactive\n", ""), data=str(tmp_path), config=str(tmp_path / "no"))
    assert state["healthy"] is False and "Fix: run the registry_mirror role." in state["errors"][1]
    assert state["repositories"] == {} and state["images"] == 0


def test_a_mirror_below_its_free_space_floor_is_marked_and_still_serves(tmp_path):
    storage(tmp_path)
    free = os.statvfs(tmp_path).f_bavail * os.statvfs(tmp_path).f_frsize
    # a floor above what this disk has free: marked; below it: not
    state = mirror_info.collect(lambda argv: (0, "active\n", ""), data=str(tmp_path), config=str(tmp_path / "c"),
                                min_free_gb=free / 1024**3 + 1)  # fmt: skip
    assert state["low_space"] is True and state["warnings"][0].startswith("LOW ON SPACE: ")
    assert "registry_mirror_gc.yml" in state["warnings"][0]
    state = mirror_info.collect(lambda argv: (0, "active\n", ""), data=str(tmp_path), config=str(tmp_path / "c"),
                                min_free_gb=0)  # fmt: skip
    assert state["low_space"] is False and "warnings" not in state
    # status's line says it after what the storage holds
    view = fleet_report.mirror_view("m1", {"mirror": dict(state, healthy=True, http_status=200,
                                                          warnings=["LOW ON SPACE: 0.3 GiB free"])})  # fmt: skip
    assert view["text"].startswith("serving (HTTP 200), ") and view["text"].endswith("; LOW ON SPACE: 0.3 GiB free")
