"""The isaac_sim_train_image module against a recording stand-in for the build host's docker (on
PATH, printing what Docker prints): the job image named by the team's image id, built only when the
cluster has none of it, never in check mode, and refused in words that name the fix."""

from __future__ import annotations

import stat

import pytest
from ansible_collections.isaacsim.fleet.plugins.modules import isaac_sim_train_image
from ansible_collections.isaacsim.fleet.tests.unit.helpers import run_module

IMAGE_ID = "sha256:0a45aaed62e1252814f088aebf8e435d91ce4f48e70df383fd5ea3fe634ad005"
DOCKER = f"""
if [ "$1 $2" = "image inspect" ]; then
  [ "$5" = isaac-lab-base:latest ] && {{ echo {IMAGE_ID}; exit 0; }}
  echo "Error: No such image: $5" >&2; exit 1
fi
if [ "$1" = save ]; then
  [ -n "$SAVE_FAILS" ] && {{ echo "Error response from daemon: no space left on device" >&2; exit 1; }}
  echo archive > "$3"; exit 0
fi
exit 2
"""


@pytest.fixture()
def build_host(tmp_path, monkeypatch):
    """A PATH with only the stand-in docker (and sh for it); each call recorded in tmp_path/calls."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    docker = bin_dir / "docker"
    docker.write_text(f'#!/bin/sh\necho "docker $*" >> "{tmp_path}/calls"\n{DOCKER}')
    docker.chmod(docker.stat().st_mode | stat.S_IEXEC)
    (bin_dir / "sh").symlink_to("/bin/sh")
    monkeypatch.setenv("PATH", str(bin_dir))
    monkeypatch.delenv("SAVE_FAILS", raising=False)
    return tmp_path


def calls(tmp_path) -> list:
    path = tmp_path / "calls"
    return path.read_text().splitlines() if path.exists() else []


def args(tmp_path, **over) -> dict:
    return dict({"source": "isaac-lab-base:latest", "runtime": "podman", "build_dir": str(tmp_path / "build")}, **over)


def test_a_build_writes_the_job_image_named_by_the_image_id(build_host, capsys):
    result = run_module(isaac_sim_train_image.main, args(build_host), capsys)
    name = "isaac-lab-base_latest-0a45aaed62e1.tar"
    assert result["changed"] and result["built"] and result["id"] == IMAGE_ID and result["file"] == name
    assert result["path"] == str(build_host / "build" / name)
    assert result["command"] == ["docker", "save", "--output", result["path"] + ".partial", "isaac-lab-base:latest"]
    # built beside the file, then moved over it
    assert (build_host / "build" / name).read_text() == "archive\n"
    assert not (build_host / "build" / f"{name}.partial").exists()


def test_nothing_is_built_when_the_cluster_has_the_image_of_this_id(build_host, capsys):
    result = run_module(isaac_sim_train_image.main, args(build_host, present=True), capsys)
    assert (result["changed"], result["built"], "command" in result) == (False, False, False)
    assert result["file"] == "isaac-lab-base_latest-0a45aaed62e1.tar"
    assert [c.split()[1] for c in calls(build_host)] == ["image"]


def test_check_mode_says_a_build_is_due_and_builds_nothing(build_host, capsys):
    result = run_module(isaac_sim_train_image.main, args(build_host, _ansible_check_mode=True), capsys)
    assert result["changed"] and result["built"] and result["command"][:2] == ["docker", "save"]
    assert not (build_host / "build").exists()
    assert [c.split()[1] for c in calls(build_host)] == ["image"]


def test_a_half_built_image_left_by_a_build_that_stopped_is_not_taken(build_host, capsys):
    (build_host / "build").mkdir()
    partial = build_host / "build" / "isaac-lab-base_latest-0a45aaed62e1.tar.partial"
    partial.write_text("half")
    result = run_module(isaac_sim_train_image.main, args(build_host), capsys)
    assert (build_host / "build" / result["file"]).read_text() == "archive\n" and not partial.exists()


def test_an_image_the_build_host_does_not_have_is_refused_naming_the_fix(build_host, capsys):
    result = run_module(isaac_sim_train_image.main, args(build_host, source="isaac-lab-other"), capsys)
    assert result["failed"] and result["msg"].startswith("train_image: 'isaac-lab-other' is not an image")
    assert "No such image: isaac-lab-other" in result["msg"] and "`docker images`" in result["msg"]


def test_a_build_tool_the_build_host_lacks_is_refused_before_anything_is_built(build_host, capsys):
    result = run_module(isaac_sim_train_image.main, args(build_host, runtime="apptainer"), capsys)
    assert result["failed"]
    assert result["msg"].startswith("train_runtime: apptainer images are built with apptainer, which the build host")
    assert not (build_host / "build").exists()
    # the cluster's copy is current: no tool is needed
    done = run_module(isaac_sim_train_image.main, args(build_host, runtime="apptainer", present=True), capsys)
    assert done["file"].endswith(".sif") and done["built"] is False


def test_a_failed_build_fails_with_its_command_and_leaves_no_image(build_host, capsys, monkeypatch):
    monkeypatch.setenv("SAVE_FAILS", "1")
    result = run_module(isaac_sim_train_image.main, args(build_host), capsys)
    assert result["failed"] and "no space left on device" in result["msg"]
    assert result["command"][:2] == ["docker", "save"] and result["msg"].startswith("docker save --output ")
    assert not (build_host / "build" / "isaac-lab-base_latest-0a45aaed62e1.tar").exists()


def test_a_build_host_without_docker_is_refused(build_host, capsys, monkeypatch):
    monkeypatch.setenv("PATH", str(build_host / "nothing"))
    result = run_module(isaac_sim_train_image.main, args(build_host), capsys)
    assert result["failed"] and result["msg"] == (
        "train_image: the build host has no docker command. Fix: build where the image is."
    )


def test_a_runtime_the_table_does_not_have_is_refused_by_the_argument_spec(build_host, capsys):
    result = run_module(isaac_sim_train_image.main, args(build_host, runtime="singularity-ce"), capsys)
    assert result["failed"] and "apptainer, podman, docker, enroot" in result["msg"]
