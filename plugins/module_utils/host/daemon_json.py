# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Merge settings into Docker's daemon.json without touching keys we do not own."""

from __future__ import annotations

import copy
import json
import os
import tempfile


class DaemonJsonError(Exception):
    pass


def merge(current: dict, settings: dict) -> dict:
    """current with settings laid over it; nested dicts merge, other values replace."""
    out = copy.deepcopy(current)
    for key, value in settings.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge(out[key], value)
        else:
            out[key] = copy.deepcopy(value)
    return out


def load(text: str | None, path: str) -> dict:
    if text is None or not text.strip():
        return {}
    try:
        data = json.loads(text)
    except ValueError as exc:
        raise DaemonJsonError(
            f"{path} is not valid JSON ({exc}); it was left as it is. Fix the file by hand, then run again."
        ) from exc
    if not isinstance(data, dict):
        raise DaemonJsonError(f"{path} must hold a JSON object; it was left as it is.")
    return data


def render(data: dict) -> str:
    return json.dumps(data, indent=2) + "\n"


def plan(text: str | None, settings: dict, path: str):
    """(changed, before_text, after_text). Changed only when the content differs, not the formatting."""
    current = load(text, path)
    wanted = merge(current, settings)
    if text is not None and wanted == current:
        return False, text, text
    return True, text or "", render(wanted)


def merge_file(path: str, settings: dict, check: bool, move) -> tuple:
    """The file at `path` with `settings` merged in: (changed, before, after), written unless `check`.
    Written whole to a temporary file beside it, then move(tmp, path) (the module's atomic_move, which
    keeps the file's SELinux context), so Docker never reads half a file. No settings and no file:
    nothing is written."""
    text = None
    if os.path.exists(path):
        with open(path) as fh:
            text = fh.read()
    if not settings and text is None:
        return False, "", "{}"
    changed, before, after = plan(text, settings, path)
    if changed and not check:
        directory = os.path.dirname(path)
        os.makedirs(directory, mode=0o755, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=directory, prefix=".daemon.json.")
        with os.fdopen(fd, "w") as fh:
            fh.write(after)
        os.chmod(tmp, 0o644)
        move(tmp, path)
    return changed, before, after
