"""The bounding box of a mask, for steps that work on a view's few changed pixels only.

Most masks of a view (its changes, a railing's footprint, the holes of one, the pixels a
neighbour sees alike) cover a few per cent of the image; labelling, filling or filtering
their box alone instead of the whole image is where several steps save most of their time
(docs/BENCHMARKS.md).
"""

from __future__ import annotations

import numpy as np


def mask_box(mask: np.ndarray, grow: int = 0) -> tuple[slice, slice] | None:
    """(rows, cols) slices of the bounding box of ``mask`` (H, W) bool's True pixels, grown by
    ``grow`` px on every side and clipped to the image; None when no pixel is True."""
    rows = np.flatnonzero(mask.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(mask.any(axis=0))
    h, w = mask.shape
    return (
        slice(max(int(rows[0]) - grow, 0), min(int(rows[-1]) + 1 + grow, h)),
        slice(max(int(cols[0]) - grow, 0), min(int(cols[-1]) + 1 + grow, w)),
    )
