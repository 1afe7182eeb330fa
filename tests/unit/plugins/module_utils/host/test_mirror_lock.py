"""The mirror's lock (module_utils/host/mirror_lock.py): one holder at a time, the waiting one told who
holds it, the lock free again once its holder ends."""

from __future__ import annotations

import pytest
from ansible_collections.isaacsim.fleet.plugins.module_utils.host import mirror_lock


def test_one_holder_at_a_time_and_the_other_waits_then_is_told_who(tmp_path):
    path = str(tmp_path / "lock" / "mirror.lock")
    waited = []
    clock = iter(range(0, 100, 2))
    other = mirror_lock.held("a garbage collection", 5, path=path, sleep=waited.append, clock=lambda: next(clock))
    busy = pytest.raises(mirror_lock.MirrorBusyError, match=r"busy with a seed of the pinned images \(pid \d+")
    with mirror_lock.held("a seed of the pinned images", 10, path=path), busy, other:
        pass
    # it waited, in steps, until its time was up
    assert waited and set(waited) == {2}
    with mirror_lock.held("a garbage collection", 0, path=path), open(path, encoding="utf-8") as f:
        assert "a garbage collection" in f.read()
