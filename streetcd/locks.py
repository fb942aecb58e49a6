"""One writer at a time: an advisory ``flock`` that fails at once instead of waiting.

Used for the change index's run lock (:func:`streetcd.index.run_lock`) and the tile store's
ingest lock (:mod:`streetcd.tiles`). The kernel drops a ``flock`` when its holder's process
ends, however it ends, so a killed run or ingest never leaves a stale lock. The file stays
(removing it would let two writers lock two different files); while held it says who holds
it. ``flock`` works across processes on one host and on NFS v4 mounts (Linux maps it to POSIX
locks there, as SQLite's own).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import socket
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from pathlib import Path


@contextlib.contextmanager
def exclusive(
    path: Path, busy: Callable[[str], Exception], what: str | None = None
) -> Iterator[None]:
    """Hold the lock file ``path`` (created) while the block runs; raise ``busy(holder)`` at
    once when another process holds it, ``holder`` being that holder as text. With ``what``
    the file describes this holder (what, process id, host, since when) while it is held;
    without, the file is never written."""
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise busy(_holder(fd)) from None
        if what is None:
            yield
            return
        holder = {
            "what": what,
            "pid": os.getpid(),
            "host": socket.gethostname(),
            "since": datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        }
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(holder).encode(), 0)
        try:
            yield
        finally:
            os.ftruncate(fd, 0)
    finally:
        os.close(fd)  # releases the lock


def _holder(fd: int) -> str:
    """The lock holder as text, from the lock file's content."""
    try:
        h = json.loads(os.pread(fd, 4096, 0).decode())
        return f"{h['what']}, process {h['pid']} on {h['host']} since {h['since']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "holder unknown: it has only just taken the lock"
