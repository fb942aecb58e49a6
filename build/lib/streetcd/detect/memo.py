"""A value derived from a numpy array, kept while that array lives.

The detector derives a few things from large arrays that many calls share: the bounding
boxes of a cloud's point runs (:func:`streetcd.detect.zbuffer.chunk_boxes`) and the checksum of a
read-only image (:meth:`streetcd.detect.cache.SurfaceCache.checksum`). Keyed by the array's
identity; since an ``id`` can be reused once its array is freed, an entry goes with its array
(a weak reference's callback) and a hit checks that the array is still the same object.
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable
from typing import Any

import numpy as np


class ArrayMemo:
    """``get(array, make)``: ``make(array)``, computed once per live array.

    ``items`` maps ``id(array)`` to (weak reference to the array, value). Arrays must not be
    changed in place after their value is made; callers decide which arrays qualify.
    """

    def __init__(self) -> None:
        self.items: dict[int, tuple[weakref.ref, Any]] = {}
        self._lock = threading.Lock()

    def get(self, array: np.ndarray, make: Callable[[np.ndarray], Any]) -> Any:
        key = id(array)
        with self._lock:
            hit = self.items.get(key)
            if hit is not None and hit[0]() is array:
                return hit[1]
        value = make(array)

        def forget(_: object) -> None:  # the array is gone: its id may be reused
            self.items.pop(key, None)

        with self._lock:
            self.items[key] = (weakref.ref(array, forget), value)
        return value
