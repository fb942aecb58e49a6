"""Progress of a run in this process, for whoever draws it (the CLI's progress bar).

The run calls :func:`notify` with ``("planned", Plan)`` once planning is done and
``("batch", list[ViewRecord])`` after each batch is published. Listeners are registered by
the caller around the run (:func:`progress_listener`), not passed through it, because the
Prefect flow's parameters travel to Prefect's server and a callback cannot.
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable, Iterator
from typing import Any

Listener = Callable[[str, Any], None]
_listeners: list[Listener] = []
_lock = threading.Lock()


@contextlib.contextmanager
def progress_listener(fn: Listener) -> Iterator[None]:
    """Call ``fn(event, payload)`` on progress in this process while the block runs."""
    with _lock:
        _listeners.append(fn)
    try:
        yield
    finally:
        with _lock:
            _listeners.remove(fn)


def notify(event: str, payload: Any) -> None:
    """Tell every listener of this process."""
    with _lock:
        listeners = list(_listeners)
    for fn in listeners:
        fn(event, payload)
