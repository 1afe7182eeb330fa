# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""NVIDIA driver version checks."""

from __future__ import annotations

import re


def version_tuple(text: str):
    """(570, 169) from "570.169" or "570.169.01"; None when it is not a version."""
    if not re.match(r"^\d+(\.\d+)*\Z", (text or "").strip()):
        return None
    return tuple(int(p) for p in text.strip().split("."))


def at_least(found: str, minimum: str) -> bool:
    f, m = version_tuple(found), version_tuple(minimum)
    if f is None or m is None:
        return False
    width = max(len(f), len(m))
    return f + (0,) * (width - len(f)) >= m + (0,) * (width - len(m))


def check(gpus, minimum, release):
    """None when every GPU's driver is new enough, else the error message."""
    if not gpus:
        return (
            "No NVIDIA GPU answered nvidia-smi on this host. Fix: install the NVIDIA driver "
            f"(at least {minimum} for Isaac Sim {release}), or set isaac_sim_gpu_enabled: false."
        )
    old = sorted({g["driver"] for g in gpus if not at_least(g["driver"], minimum)})
    if old:
        return (
            f"NVIDIA driver {', '.join(old)} is older than {minimum}, the minimum for Isaac Sim {release}. "
            f"Fix: upgrade the driver to {minimum} or newer, or choose an older isaac_sim_release."
        )
    return None
