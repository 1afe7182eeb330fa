"""The instances' persistent directories (module_utils/host/dirs.py)."""

from __future__ import annotations

import os
import stat

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import dirs

UID, GID = os.getuid(), os.getgid()


def test_creates_missing_and_then_has_nothing_to_do(tmp_path):
    paths = [str(tmp_path / "i0"), str(tmp_path / "i0" / "cache" / "main")]
    changes = dirs.wanted_changes(paths, UID, GID, 0o750)
    assert changes == [(paths[0], "create"), (paths[1], "create")]
    dirs.apply(changes, UID, GID, 0o750)
    assert stat.S_IMODE(os.stat(paths[1]).st_mode) == 0o750
    assert dirs.wanted_changes(paths, UID, GID, 0o750) == []


def test_fixes_mode_and_keeps_content(tmp_path):
    d = tmp_path / "cache"
    d.mkdir(mode=0o777)
    (d / "shader.bin").write_text("warm")
    os.chmod(d, 0o777)
    changes = dirs.wanted_changes([str(d)], UID, GID, 0o750)
    assert changes == [(str(d), "mode")]
    dirs.apply(changes, UID, GID, 0o750)
    assert (d / "shader.bin").read_text() == "warm"


def test_wrong_owner_is_reported(tmp_path):
    assert dirs.wanted_changes([str(tmp_path)], UID + 1, GID, stat.S_IMODE(os.stat(tmp_path).st_mode)) == [
        (str(tmp_path), "owner")
    ]


def test_a_file_in_the_way_is_left_alone(tmp_path):
    f = tmp_path / "logs"
    f.write_text("user data")
    changes = dirs.wanted_changes([str(f)], UID, GID, 0o750)
    with pytest.raises(OSError, match="not a directory"):
        dirs.apply(changes, UID, GID, 0o750)
    assert f.read_text() == "user data"
