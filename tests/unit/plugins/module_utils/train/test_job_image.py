"""job_image.ensure on a build host made of functions: which program it looks for, what it runs,
per runtime (the build tool is the runtime table's)."""

from __future__ import annotations

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.train import job_image, runtimes

IMAGE_ID = "sha256:0a45aaed62e1252814f0"


def host(tools, ran):
    def run(argv):
        ran.append(argv)
        if argv[1:3] == ["image", "inspect"]:
            return 0, IMAGE_ID + "\n", ""
        open(argv[-2] if argv[0] == "apptainer" else argv[argv.index("--output") + 1], "w").close()
        return 0, "", ""

    return job_image.BuildHost(lambda name: f"/usr/bin/{name}" if name in tools else None, run)


@pytest.mark.parametrize("runtime", list(runtimes.RUNTIMES))
def test_each_runtime_is_built_with_its_tool_into_a_file_named_by_the_image_id(runtime, tmp_path):
    ran = []
    tool = runtimes.RUNTIMES[runtime]["build_tool"]
    result = job_image.ensure(host({"docker", tool}, ran), "lab:1", runtime, str(tmp_path))
    suffix = runtimes.RUNTIMES[runtime]["image_suffix"]
    assert result["file"] == f"lab_1-0a45aaed62e1{suffix}" and (tmp_path / result["file"]).exists()
    assert ran[0] == ["/usr/bin/docker", "image", "inspect", "--format", "{{.Id}}", "lab:1"]
    assert ran[1] == result["command"] and ran[1][0] == tool


def test_without_the_runtime_s_build_tool_nothing_is_run_but_the_inspect(tmp_path):
    ran = []
    with pytest.raises(job_image.ImageError, match="enroot images are built with enroot"):
        job_image.ensure(host({"docker"}, ran), "lab:1", "enroot", str(tmp_path))
    assert len(ran) == 1
