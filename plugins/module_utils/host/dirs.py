# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Bring a set of directories to one owner and mode in a single pass."""

from __future__ import annotations

import os
import stat


def wanted_changes(paths, uid: int, gid: int, mode: int):
    """[(path, what)] for each directory missing or with another owner or mode."""
    changes = []
    for path in paths:
        try:
            st = os.lstat(path)
        except FileNotFoundError:
            changes.append((path, "create"))
            continue
        if not stat.S_ISDIR(st.st_mode):
            changes.append((path, "not a directory"))
            continue
        if (st.st_uid, st.st_gid) != (uid, gid):
            changes.append((path, "owner"))
        if stat.S_IMODE(st.st_mode) != mode:
            changes.append((path, "mode"))
    return changes


def apply(changes, uid: int, gid: int, mode: int):
    for path, what in changes:
        if what == "not a directory":
            raise OSError(f"{path} exists and is not a directory; it was left as it is")
        if what == "create":
            os.makedirs(path, exist_ok=True)
        os.chown(path, uid, gid)
        os.chmod(path, mode)
