# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""Merge settings into Docker's daemon.json without touching keys we do not own."""

from __future__ import annotations

import copy
import json


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
