# Copyright: isaacsim.fleet contributors
# SPDX-License-Identifier: Apache-2.0 (the collection's license, see galaxy.yml)
"""A host's finished runs until a controller has them.

A run's directory (DATA_ROOT/runs/RUN) is finished once it holds result.json. The controller
that started the run brings it back and removes it (or marks it fetched, when it keeps runs on
the host). A controller that went away (killed, its connection dropped) leaves it behind: once
it has waited `unfetched_after` seconds, the next run on the host takes it and brings it back
with its own. Directories older than the retention limit go, fetched or not, and so do bundles
(the tar files runs are carried in) that nobody fetched: they are copies.

Taking is one critical section under flock(2), so two runs never both take one directory.
"""

from __future__ import annotations

import fcntl
import os
import secrets
import tarfile

RESULT = "result.json"
FETCHED = ".fetched"  # a run kept on the host (experience_keep_on_host) that a controller has
TAKEN = ".taken"  # when a run last handed this directory to a controller
BUNDLE_SUFFIX = ".tar.gz"
GUARD = ".store.lock"
DAY_S = 86400


def classify(entries: list, live, now: float, unfetched_after: float, keep_s: float, ended=()) -> tuple:
    """(to take, to remove) among a store's entries.

    entries: {"name", "bundle": bool, "mtime", "finished": result.json's mtime or None,
    "fetched": bool, "taken": .taken's mtime or None}. live: runs still going (never touched).
    keep_s: 0 keeps runs for ever. A run still waiting for its own controller is left alone:
    unfetched_after counts from its end, or from the last time another run took it; a run in
    `ended` (its runner died, so no controller waits for it) is taken at once."""
    take, remove = [], []
    for entry in sorted(entries, key=lambda e: e["name"]):
        name = entry["name"]
        if entry.get("bundle"):
            if now - entry["mtime"] >= max(unfetched_after, 0):
                remove.append(name)
            continue
        if name in live:
            continue
        since = entry["finished"] if entry.get("finished") is not None else entry["mtime"]
        if keep_s and now - since >= keep_s:
            remove.append(name)
            continue
        if entry.get("finished") is None or entry.get("fetched"):
            continue
        handed = max(entry["finished"], entry.get("taken") or 0)
        if now - handed >= unfetched_after or (name in ended and not entry.get("taken")):
            take.append(name)
    return take, remove


def _mtime(path: str):
    try:
        return os.stat(path).st_mtime
    except FileNotFoundError:
        return None


def entries(root: str) -> list:
    """What a store (DATA_ROOT/runs) holds: run directories and bundles."""
    found = []
    try:
        listing = list(os.scandir(root))
    except FileNotFoundError:
        return found
    for item in listing:
        if item.name.startswith("."):
            continue
        if item.is_file(follow_symlinks=False) and item.name.endswith(BUNDLE_SUFFIX):
            found.append({"name": item.name, "bundle": True, "mtime": item.stat().st_mtime})
        elif item.is_dir(follow_symlinks=False):
            found.append(
                {
                    "name": item.name,
                    "bundle": False,
                    "mtime": item.stat().st_mtime,
                    "finished": _mtime(os.path.join(item.path, RESULT)),
                    "fetched": os.path.exists(os.path.join(item.path, FETCHED)),
                    "taken": _mtime(os.path.join(item.path, TAKEN)),
                }
            )
    return found


def take(root: str, live, now: float, unfetched_after: float, keep_days: float, remove, ended=()) -> tuple:
    """Take the finished runs no controller fetched, and remove what is past the retention
    limit. Returns (taken, removed) names; each taken directory is marked so no other run takes
    it for the next `unfetched_after` seconds. remove(path) removes a file or directory."""
    os.makedirs(root, mode=0o755, exist_ok=True)
    with open(os.path.join(root, GUARD), "a") as guard:
        fcntl.flock(guard, fcntl.LOCK_EX)
        taken, removed = classify(entries(root), set(live), now, unfetched_after, keep_days * DAY_S, set(ended))
        for name in removed:
            remove(os.path.join(root, name))
        for name in taken:
            with open(os.path.join(root, name, TAKEN), "w"):
                pass
            os.utime(os.path.join(root, name, TAKEN), (now, now))
    return taken, removed


def pack(root: str, names) -> tuple:
    """One gzip'd tar of the named run directories (a directory each, by its name), in the store
    itself: one fetch per run, not one per file. Returns (path, names packed); a directory that
    is gone (another run's controller removed it) is left out."""
    path = os.path.join(root, f"bundle-{secrets.token_hex(4)}{BUNDLE_SUFFIX}")
    packed = []

    def markers_out(info):
        return None if os.path.basename(info.name) in (TAKEN, FETCHED) else info

    with tarfile.open(path, "w:gz") as tar:
        for name in names:
            if os.path.isdir(os.path.join(root, name)):
                tar.add(os.path.join(root, name), arcname=name, filter=markers_out)
                packed.append(name)
    return path, packed
