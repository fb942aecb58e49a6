"""One writer at a time: an advisory ``flock`` that fails at once instead of waiting.

Used for the change index's run lock (:func:`run_lock`, below) and the tile store's ingest
lock (:mod:`streetcd.store.ingest`). The kernel drops a ``flock`` when its holder's process
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

from streetcd.errors import IndexBusyError


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


# --- the change index's run lock ----------------------------------------------------------


def lock_path(index: str | Path) -> Path:
    """The run lock file of the change index at ``index``: ``<index>.lock`` beside it."""
    return Path(f"{index}.lock")


@contextlib.contextmanager
def run_lock(index: str | Path, what: str = "a streetcd run") -> Iterator[Path]:
    """Hold the run lock of the change index at ``index`` while the block runs.

    Fails at once with :class:`IndexBusyError`, naming the holder (what, process id, host,
    since when) when another run holds it; nothing is changed then. Two runs on one index
    would plan the same views and detect them twice (the index stays consistent, but the
    second run's work is wasted and its counts are wrong), so the second one stops rather
    than waits: a nightly job that finds last night's run still going should say so, not
    queue up behind it.

    The lock is :func:`exclusive` on ``<index>.lock`` (an advisory ``flock``, dropped by the
    kernel with its holder); the file describes the holder while held, nothing after.
    """
    path = lock_path(index)
    path.parent.mkdir(parents=True, exist_ok=True)

    def busy(holder: str) -> IndexBusyError:
        return IndexBusyError(
            f"change index {index} is in use by another run ({holder}; lock file "
            f"{path}); wait for it to finish. Nothing was changed."
        )

    with exclusive(path, busy, what):
        yield path
