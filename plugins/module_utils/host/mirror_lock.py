# Copyright: isaacsim.fleet contributors
# Apache-2.0
"""One change of the mirror's storage at a time: a seed (mirror_seed.py) and a garbage collection
(mirror_gc.py) each hold this lock on the mirror host for their whole time. Deploys from two
inventories may share one mirror; the seed's loopback registry has one unit name, and a seed that
found it running would stop the other's copy, and a collection could drop what a seed copies.

flock(2) on a file in /run/lock: released when the module's process ends, however it ends; the
file names the holder for the one who waits.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import time

LOCK = "/run/lock/isaac-sim-mirror.lock"


class MirrorBusyError(Exception):
    pass


@contextlib.contextmanager
def held(what: str, timeout: float, path: str | None = None, sleep=time.sleep, clock=time.monotonic):
    """Hold the mirror's lock for `what` (said to the one who waits), waiting up to `timeout` seconds."""
    path = path or LOCK
    os.makedirs(os.path.dirname(path), exist_ok=True)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o600)
    try:
        deadline = clock() + timeout
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError as exc:
                if clock() >= deadline:
                    holder = os.pread(fd, 512, 0).decode(errors="replace").strip() or "another run"
                    raise MirrorBusyError(
                        f"the mirror is busy with {holder} after {int(timeout)} s of waiting; nothing was changed. "
                        "Fix: run again once it has ended."
                    ) from exc
                sleep(2)
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{what} (pid {os.getpid()}, since {time.strftime('%H:%M:%S UTC', time.gmtime())})".encode(), 0)
        yield
    finally:
        os.close(fd)
