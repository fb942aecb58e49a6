"""streetcd.detect.boxes: the bounding box of a mask."""

from __future__ import annotations

import numpy as np

from streetcd.detect.boxes import mask_box


def test_the_box_of_a_mask_grown_and_clipped_to_the_image():
    mask = np.zeros((20, 30), bool)
    assert mask_box(mask) is None and mask_box(mask, 5) is None
    mask[3, 4] = mask[9, 25] = True
    assert mask_box(mask) == (slice(3, 10), slice(4, 26))
    assert mask_box(mask, 2) == (slice(1, 12), slice(2, 28))
    assert mask_box(mask, 10) == (slice(0, 20), slice(0, 30))  # clipped
    rows, cols = mask_box(mask)
    assert mask[rows, cols].sum() == mask.sum()
