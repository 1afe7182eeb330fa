"""Which GPUs have a video encoder (module_utils/instance/nvenc.py): the driver's encode API, asked
through ctypes in a child process.

The program itself runs here against the stand-in driver libraries (tests/fixtures/nvidia-driver:
libcuda.so.1 and libnvidia-encode.so.1, built from C with gcc, as strict as nvEncodeAPI.h for
every struct version); on real hardware it ran on an H100 (tests/unit/recorded/h100-nvenc-probe.json).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.instance import nvenc
from ansible_collections.isaacsim.fleet.tests.unit.helpers import recorded

FIXTURE = Path(__file__).resolve().parents[4] / "fixtures" / "nvidia-driver"
MIXED = "NVIDIA H100 80GB HBM3:81559:no:NVIDIA|NVIDIA L4:23034:yes:NVIDIA|NVIDIA L4:23034:yes:NVIDIA"


def test_a_real_h100_has_no_encoder_though_nvml_says_full_capacity():
    """Recorded on an H100 80GB HBM3, driver 580.159.04: the encode API refuses the device
    (NV_ENC_ERR_UNSUPPORTED_DEVICE), while NVML's encoder capacity for H.264 read 100 %."""
    found, error = nvenc.read(recorded("h100-nvenc-probe.json"))
    assert error is None
    assert found == {"GPU-3a4bf3b5-f6d5-6f6e-6ea6-9e95c4b58413": False}
    nvml = json.loads(recorded("h100-nvml.json"))
    assert nvml["gpus"][0]["nvmlDeviceGetEncoderCapacity(NVML_ENCODER_QUERY_H264)"]["value"] == 100


@pytest.mark.parametrize(
    "status, answer",
    [(0, True), (nvenc.NO_ENCODE_DEVICE, False), (nvenc.UNSUPPORTED_DEVICE, False), (8, None), (None, None)],
)
def test_only_the_two_no_device_statuses_mean_no_encoder(status, answer):
    gpu = {"ordinal": 0, "uuid": "GPU-a"}
    if status is not None:
        gpu["status"] = status
    assert nvenc.read(json.dumps({"gpus": [gpu], "error": None})) == ({"GPU-a": answer}, None)


def test_a_probe_that_could_not_ask_says_why_and_finds_nothing():
    text = json.dumps({"gpus": [], "error": "libnvidia-encode.so.1 (the driver's encode library) could not be loaded"})
    assert nvenc.read(text) == ({}, "libnvidia-encode.so.1 (the driver's encode library) could not be loaded")
    assert nvenc.read("Segmentation fault")[1].startswith("the encoder probe printed no answer")
    assert nvenc.read("")[1] == "the encoder probe printed no answer"
    assert nvenc.probe(lambda argv: (139, "", "Segmentation fault"), "python3") == (
        {},
        "the encoder probe exited 139: Segmentation fault",
    )


@pytest.fixture(scope="module")
def driver_libs(tmp_path_factory):
    out = tmp_path_factory.mktemp("standin-driver")
    subprocess.run([str(FIXTURE / "build"), str(out)], check=True)
    return out


def run_probe(libs, tmp_path, config):
    conf, log = tmp_path / "standin.conf", tmp_path / "standin.log"
    conf.write_text(config)
    env = dict(os.environ, LD_LIBRARY_PATH=str(libs), STANDIN_NVIDIA_CONF=str(conf), STANDIN_NVIDIA_LOG=str(log))

    def run(argv):
        proc = subprocess.run(argv, capture_output=True, text=True, env=env, check=False)
        return proc.returncode, proc.stdout, proc.stderr

    found, error = nvenc.probe(run, sys.executable)
    return found, error, log.read_text().splitlines() if log.exists() else []


def test_the_probe_asks_each_gpu_and_closes_what_it_opens(driver_libs, tmp_path):
    found, error, log = run_probe(driver_libs, tmp_path, f"STANDIN_GPU_MODELS='{MIXED}'\n")
    assert error is None
    assert found == {
        "GPU-00000000-0000-0000-0000-000000000000": False,
        "GPU-00000000-0000-0000-0000-000000000001": True,
        "GPU-00000000-0000-0000-0000-000000000002": True,
    }
    # the stand-in refuses any struct or API version but its own: status 0 proves the layout
    assert log == [
        "open gpu=0 status=2",
        "open gpu=1 status=0",
        "destroy gpu=1",
        "open gpu=2 status=0",
        "destroy gpu=2",
    ]


def test_without_the_encode_library_nothing_is_known(driver_libs, tmp_path):
    (tmp_path / "only-cuda").mkdir()
    (tmp_path / "only-cuda" / "libcuda.so.1").symlink_to(driver_libs / "libcuda.so.1")
    found, error, _log = run_probe(tmp_path / "only-cuda", tmp_path, "STANDIN_GPUS=1\n")
    assert found == {}
    assert "libnvidia-encode.so.1 (the driver's encode library) could not be loaded" in error


def test_no_gpu_is_said_not_guessed(driver_libs, tmp_path):
    found, error, _log = run_probe(driver_libs, tmp_path, "STANDIN_GPUS=0\n")
    assert found == {} and error == "cuInit returned 100"


def test_a_probe_that_hangs_is_ended_and_said():
    seen = []

    def run(argv):
        seen.append(argv)
        return 124, "", ""

    assert nvenc.probe(run, "python3", "/usr/bin/timeout") == (
        {},
        f"the encoder probe did not answer within {nvenc.TIMEOUT_S} s (the driver hangs)",
    )
    assert seen[0][:4] == ["/usr/bin/timeout", "-k", "5", str(nvenc.TIMEOUT_S)] and seen[0][4:6] == ["python3", "-c"]
