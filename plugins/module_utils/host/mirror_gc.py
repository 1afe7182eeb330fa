# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""The registry mirror's garbage collection (module isaac_sim_mirror_gc, playbooks/registry_mirror_gc.yml):
every manifest the fleet's instances do not run or pin is dropped from the mirror's storage, then
the registry's own `garbage-collect` deletes the blobs no remaining manifest references (blobs
shared with a kept image stay). The registry is stopped meanwhile (Distribution's collector must
not run beside a registry that writes) and started again, failed or not.
"""

from __future__ import annotations

import json
import os
import shutil

from ansible_collections.isaacsim.fleet.plugins.module_utils.host import mirror_info, mirror_seed, registry_mirror


def children(read, digest: str) -> list:
    """The images of an index (manifest list), or [] for an image's manifest or one not held."""
    data = read(mirror_seed.blob_path(digest))
    if data is None:
        return []
    try:
        return [m["digest"] for m in json.loads(data).get("manifests") or []]
    except (ValueError, KeyError, TypeError, AttributeError):
        return []


def doomed(read, held: list, keep: list) -> list:
    """The (repository, digest) of held that neither is a kept digest nor an image of a kept index."""
    kept = set(keep)
    for digest in list(kept):
        kept.update(children(read, digest))
    return [(name, digest) for name, digest in held if digest not in kept]


class GcError(Exception):
    pass


class Collector:
    """The I/O of a collection on the mirror host. run(argv) -> (rc, out, err)."""

    def __init__(self, run, data: str = registry_mirror.DATA, config=f"{registry_mirror.CONFIG_DIR}/config.yml"):
        self.run = run
        self.data = data
        self.store = data + mirror_seed.STORE[len(registry_mirror.DATA) :]
        self.config = config

    def read(self, path: str):
        return mirror_seed.read_under(self.store, path)

    def plan(self, keep: list) -> list:
        return doomed(self.read, mirror_seed.manifests(self.store), keep)

    def drop(self, images: list) -> None:
        """Each manifest's revision, and every tag of its repository that names it."""
        for name, digest in images:
            repo = os.path.join(self.store, "repositories", name, "_manifests")
            shutil.rmtree(os.path.join(repo, "revisions", *digest.split(":", 1)), ignore_errors=True)
            tags = os.path.join(repo, "tags")
            for tag in sorted(os.listdir(tags)) if os.path.isdir(tags) else []:
                current = os.path.join(tags, tag, "current", "link")
                try:
                    with open(current, encoding="utf-8") as f:
                        named = f.read().strip()
                except OSError:
                    continue
                if named == digest:
                    shutil.rmtree(os.path.join(tags, tag), ignore_errors=True)

    def collect(self, images: list) -> int:
        """Drop images, delete what nothing references; the bytes freed."""
        before = mirror_info.used_bytes(self.data)
        rc, out, err = self.run(["systemctl", "stop", registry_mirror.UNIT])
        if rc != 0:
            raise GcError(f"could not stop {registry_mirror.UNIT}: {(out + err).strip()[-400:]}")
        try:
            self.drop(images)
            # as the registry's user: what it deletes and leaves stays that user's
            rc, out, err = self.run(
                ["runuser", "-u", registry_mirror.USER, "--", registry_mirror.REGISTRY, "garbage-collect", self.config]
            )
            if rc != 0:
                raise GcError(f"the registry's garbage-collect failed: {(out + err).strip()[-600:]}")
        finally:
            self.run(["systemctl", "start", registry_mirror.UNIT])
        return before - mirror_info.used_bytes(self.data)
