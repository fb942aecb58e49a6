"""Each neighbour registered to the view by one whole-image shift before eq. 5 (not in the
paper; issue 16).

Eq. 5 compares a view's pixel with a neighbour's colour where the old surface sends it, and
tolerates registration error only within its colour envelope
(``correlate.registration_tolerance_px``: 2 px at 1920 wide, 1 px at 1280). Poses from a
bundle adjustment are off by a few pixels, and to first order that error is one shift of the
whole image per view (a small rotation of the camera); between a view and a neighbour the two
add up. Beyond the envelope every edge of the old surface shows as change along its outline,
and the graph cut joins those lines into false regions.

Here each neighbour is warped through the view's old surface (eq. 4) at the texture cue's
working size (:func:`~streetcd.detect.texture.work_size`), and the whole-pixel shift that best
correlates it with the view, over the pixels both see away from the street inventory whose
change is looked for (:func:`~streetcd.detect.texture.shift_search`, the texture cue's search
carried down to the working size's own pixels), becomes the neighbour's :attr:`~streetcd.detect.correlate.Neighbour.offset`:
eq. 5 then reads the old surface at the view's pixel less that shift. A shift is kept only
when it correlates better than none by ``min_gain`` and lies inside the search: one at the
search's edge is a slope of the correlation, not its peak. A sparse cloud with little texture
on it, or a side camera of a moving rig, keeps its pose as given (on the real case's unchanged
twin, shifts at the edge flagged two views of 18 before that test: docs/TUNING.md,
twenty-fifth round).
"""

from __future__ import annotations

import numpy as np

from streetcd.config import TextureParams, scale_px
from streetcd.detect.texture import (
    WorkingView,
    background_mask,
    shift_correlation,
    shift_search,
    work_scale,
)


def neighbour_shifts(
    working: WorkingView,
    width: int,
    where: np.ndarray | None,
    params: TextureParams,
    max_shift_px: float,
    min_gain: float,
) -> list[tuple[float, float]]:
    """The shift (dy, dx) of each neighbour against the view, in the view's full-resolution
    pixels: eq. 5 compares the view's pixel (y, x) with what the neighbour sees of the old
    surface at (y − dy, x − dx). (0.0, 0.0) where no shift is kept (module doc).

    working : the view and its neighbours at the texture cue's working size
    (:func:`~streetcd.detect.texture.working_view`). width : the view's width (px). where :
    (H, W) bool, the pixels whose change is looked for (the shift is measured more than a
    texture window away from them), or None. params : the texture cue's (working size,
    window). max_shift_px : the largest shift looked for, px at ``REFERENCE_WIDTH_PX``.
    min_gain : how much better than no shift the best must correlate (band-passed grey
    levels, a correlation in [−1, 1]).
    """
    s = work_scale(params, width)
    search = round(scale_px(max_shift_px, width, minimum=0.0) * s)
    if search < 2:  # a search of one pixel: every shift it finds lies at its edge
        return [(0.0, 0.0)] * len(working.warps)
    small = (working.depth.shape[1], working.depth.shape[0])
    whole = (slice(0, small[1]), slice(0, small[0]))
    background = background_mask(where, small, whole, params.window_px)
    shifts = []
    for warped, seen in working.warps:
        valid = seen & background
        dy, dx, best, passed = shift_search(working.grey, warped, valid, search, finest_level=0)
        if (dy, dx) != (0, 0):
            at_edge = max(abs(dy), abs(dx)) >= search
            unshifted, _ = shift_correlation(*passed, 0, 0)
            if at_edge or best - (0.0 if np.isnan(unshifted) else unshifted) < min_gain:
                dy = dx = 0
        shifts.append((dy / s, dx / s))
    return shifts
