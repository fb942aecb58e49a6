"""A command's work in a child process that cannot outlive the command: no orphans.

``streetcd run`` starts Prefect's temporary server (uvicorn, ~190 MB) and a Dask LocalCluster
(a scheduler and worker processes) as subprocesses. Killed with SIGKILL, a process cannot stop
them, so they kept running. So the command is a small supervisor (:func:`run_supervised`)
and the night runs in a child started in a session, and so a process group, of its own;
whatever the child starts stays in that group (neither Prefect's server nor Dask's processes
call ``setsid``; ``tests/test_orphans.py`` checks). Then:

- the supervisor killed in any way (SIGKILL included): the child's watchdog
  (:func:`watch_supervisor`) sees the pipe from the supervisor close and kills its whole group;
- SIGTERM, SIGINT (Ctrl-C) or SIGHUP to the supervisor: forwarded to the child, which
  stops what it started; a second one, or a child still there after :data:`GRACE_S`, sends
  SIGKILL to the whole group;
- the child ends: what is left of its group is killed, and the supervisor returns the
  child's exit code unchanged (128 + N for a child killed by signal N, as shells report it).

The watchdog blocks on a pipe rather than polling ``os.getppid()``: the kernel closes the
supervisor's write end the moment it dies, so the group goes at once, and a pipe works the
same on macOS. Standard library only; POSIX only (:func:`supported`).
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from typing import IO, Any

# The child finds the read end of the supervisor's pipe under this name (a file descriptor).
SUPERVISOR_FD_ENV = "STREETCD_SUPERVISOR_FD"
# Seconds a child's group has to stop after a forwarded signal before it gets SIGKILL.
# Long enough for a night to close a LocalCluster on a busy 2-core machine (10 s was not).
GRACE_S = 20.0
FORWARDED = ("SIGTERM", "SIGINT", "SIGHUP")


def supported() -> bool:
    """Whether this platform has process groups and sessions (Linux, macOS; not Windows)."""
    return hasattr(os, "killpg") and hasattr(os, "setsid")


def run_supervised(cmd: Sequence[str], env: dict[str, str] | None = None) -> int:
    """Run ``cmd`` as a supervised child (see the module's docstring); its exit code.

    The child must call :func:`watch_supervisor` first thing. Its stdout and stderr are this
    process's file descriptors where ``sys.stdout`` / ``sys.stderr`` have one (a terminal
    keeps its progress bar), else they are copied into those streams (click's test runner,
    pytest's capture).
    """
    sys.stdout.flush()
    sys.stderr.flush()
    read_end, write_end = os.pipe()  # not inheritable: only the read end is passed on
    out_fd, err_fd = _fileno(sys.stdout), _fileno(sys.stderr)
    child = subprocess.Popen(
        list(cmd),
        env={**(os.environ if env is None else env), SUPERVISOR_FD_ENV: str(read_end)},
        pass_fds=(read_end,),
        start_new_session=True,
        stdout=subprocess.PIPE if out_fd is None else out_fd,
        stderr=subprocess.PIPE if err_fd is None else err_fd,
    )
    os.close(read_end)
    relays = [_relay(child.stdout, sys.stdout), _relay(child.stderr, sys.stderr)]
    try:
        with _forwarding_signals(child.pid) as forwarded_at:
            code = _wait(child, forwarded_at)
    finally:
        _kill_group(child.pid, signal.SIGKILL)  # whatever is left of it
        child.wait()
        os.close(write_end)
        for relay in relays:
            if relay is not None:
                relay.join(timeout=5)
    return code if code >= 0 else 128 - code


def watch_supervisor() -> None:
    """In a child of :func:`run_supervised`: kill this process's whole group when the
    supervisor dies. Does nothing in a process not started that way."""
    fd = os.environ.pop(SUPERVISOR_FD_ENV, None)  # not for the processes we start
    if fd is None or not supported():
        return
    if os.getpgrp() != os.getpid():  # never kill a group that is not our own
        return

    def watch() -> None:
        with contextlib.suppress(OSError):
            while os.read(int(fd), 1):  # the supervisor never writes: this waits for EOF
                pass
        os.killpg(os.getpgrp(), signal.SIGKILL)

    threading.Thread(target=watch, name="streetcd-supervisor-watch", daemon=True).start()


def _wait(child: subprocess.Popen[bytes], forwarded_at: list[float]) -> int:
    """The child's return code, once it ends; SIGKILL to its group :data:`GRACE_S` after a
    forwarded signal."""
    while True:
        try:
            return child.wait(timeout=0.2)
        except subprocess.TimeoutExpired:
            if forwarded_at and time.monotonic() - forwarded_at[0] > GRACE_S:
                _kill_group(child.pid, signal.SIGKILL)


@contextlib.contextmanager
def _forwarding_signals(pgid: int) -> Iterator[list[float]]:
    """Forward :data:`FORWARDED` signals to the child ``pgid`` (its group's leader) while inside; yields the times
    of the signals forwarded. Handlers can only be set in the main thread; elsewhere the
    signals keep their own handling (and the ``finally`` above still kills the group)."""
    forwarded_at: list[float] = []
    if threading.current_thread() is not threading.main_thread():
        yield forwarded_at
        return

    def forward(signum: int, frame: Any) -> None:
        # To the child alone, which stops what it started (Prefect records the run as
        # crashed on its server, which must still be up for that); a second signal (Ctrl-C
        # twice) means now, to the whole group.
        if forwarded_at:
            _kill_group(pgid, signal.SIGKILL)
        else:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pgid, signum)
        forwarded_at.append(time.monotonic())

    signums = [getattr(signal, name) for name in FORWARDED if hasattr(signal, name)]
    previous = {s: signal.signal(s, forward) for s in signums}
    try:
        yield forwarded_at
    finally:
        for s, handler in previous.items():
            # None: a handler not set from Python, which cannot be put back; the default then.
            signal.signal(s, signal.SIG_DFL if handler is None else handler)


def _kill_group(pgid: int, signum: int) -> None:
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(pgid, signum)


def _fileno(stream: IO[str]) -> int | None:
    """``stream``'s file descriptor, or None for an in-memory stream."""
    try:
        return stream.fileno()
    except (AttributeError, OSError, ValueError):  # io.UnsupportedOperation is both
        return None


def _relay(pipe: IO[bytes] | None, stream: IO[str]) -> threading.Thread | None:
    """Copy ``pipe`` into ``stream`` in a thread until the pipe closes."""
    if pipe is None:
        return None

    def copy() -> None:
        with pipe:
            for line in pipe:
                stream.write(line.decode("utf-8", "replace"))
                stream.flush()

    thread = threading.Thread(target=copy, name="streetcd-relay", daemon=True)
    thread.start()
    return thread
