"""The store's one-writer lock: an exclusive ``flock`` on ``DIR/.writer.lock`` holding the
writer's pid (a second writer waits ``lock_timeout_s``, then gets StoreLockedError)."""

from __future__ import annotations

import contextlib
import fcntl
import os
import time
from pathlib import Path

from icbtool.store.base import (
    LOCK_NAME,
    StoreLockedError,
)


def _acquire_lock(root: Path, timeout_s: float) -> int:
    """Take the store's writer lock (an exclusive flock); returns the open file descriptor."""
    fd = os.open(root / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            break
        except BlockingIOError:
            if time.monotonic() >= deadline:
                try:
                    holder = os.pread(fd, 64, 0).decode(errors="replace").strip()
                except OSError:
                    holder = "?"
                os.close(fd)
                raise StoreLockedError(
                    f"store {root} is open for writing by another process (pid {holder}); "
                    f"waited {timeout_s} s. Open it with StoreConfig(readonly=True) to read."
                ) from None
            time.sleep(0.05)
    os.ftruncate(fd, 0)
    os.pwrite(fd, str(os.getpid()).encode(), 0)
    return fd


def _release_lock(fd: int) -> None:
    with contextlib.suppress(OSError):
        fcntl.flock(fd, fcntl.LOCK_UN)
    os.close(fd)
