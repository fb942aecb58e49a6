"""Pixel outline of each changed region, by colour (GrabCut in a band around the region).

**Not in the paper.** The paper's graph (eq. 6) has a node per pixel; it cuts on superpixels
for speed (§3.4), and so do we (:mod:`streetcd.detect.graphcut`): a region's outline is then made of
superpixel edges. A 24 px superpixel straddles a 12 px pole and the wall beside it, the
superpixel's mean change is diluted and half of the pole is lost; a superpixel that straddles
a board's edge is all in or all out. On the synthetic streets 55 % of the missed pixels lie
within half a superpixel of the detected mask (``docs/TUNING.md``).

The outline is redrawn at pixel level with GrabCut (Rother, Kolmogorov & Blake 2004, in
OpenCV): colour models (Gaussian mixtures) of the region and of its surroundings and a
pixel graph cut with contrast-sensitive smoothness, the same kind of energy as eq. 6–8 with
colour as the evidence. It runs in a window around each region (regions whose windows
would overlap share one, and one pair of colour models), and may only move the outline
within ``band_px`` of where the superpixel cut put it:

* the region shrunk by the band is the object (fixed);
* the rest of the region is probably the object, the band outside it probably not;
* beyond the band is not the object (fixed), and is what the background model learns from.

So no region spreads along a wall and none wider than twice the band vanishes: what the
graph cut of eq. 6 decided stays decided at the scale of a superpixel, and only the outline
follows the image (a sliver narrower than that may go, if its colours are the
surroundings'). The speckle filter then runs again on the result. GrabCut's k-means draws
from OpenCV's random generator, which is reseeded before every call: a view gives the
same mask on every run.
"""

from __future__ import annotations

import cv2
import numpy as np

from streetcd.config import DetectParams, RefineParams, scale_px
from streetcd.detect.boxes import mask_box
from streetcd.detect.graphcut import speckle_filter, speckle_min_px

_DEFAULTS = RefineParams()
# The window around a group of regions reaches one more band width and MIN_RING_PX beyond
# the band: the background colour model learns from that ring.
MIN_RING_PX = 4
RNG_SEED = 0x5C4D  # see _grabcut
# GrabCut runs on windows scaled so that the band is about this wide: 3/4 of a 1920 px
# view (band 12 px), 0.36 of a 4000 px one (band 25 px), so a 12 MP view's outlines cost
# about what a 2 MP view's do. Its max-flow dominates (time per window pixel:
# docs/BENCHMARKS.md); 12 px at 1920 px kept 0.006 more kappa on one of two streets for
# twice the time (docs/TUNING.md).
WORK_BAND_PX = 9


def refined_mask(image: np.ndarray, mask: np.ndarray, params: DetectParams) -> np.ndarray:
    """The cut's ``mask`` (H, W) bool after :func:`refine_outline` and the speckle filter
    again, as :func:`streetcd.detect.chain.detect_view` gives it; ``mask`` itself when
    ``params.refine`` is off or nothing changed. image : (H, W, 3) uint8, the view."""
    if not params.refine.enabled or not mask.any():
        return mask
    width = image.shape[1]
    refined = refine_outline(image, mask, width, params.refine)
    return speckle_filter(refined, speckle_min_px(width, params.graphcut))


def refine_outline(
    image: np.ndarray, mask: np.ndarray, width_px: int, params: RefineParams = _DEFAULTS
) -> np.ndarray:
    """The changed regions of ``mask`` with their outlines redrawn by colour (module doc).

    image : (H, W, 3) uint8, the view. mask : (H, W) bool, the cut's changed pixels.
    width_px : the image width that ``band_px`` (given at ``REFERENCE_WIDTH_PX``) scales to.
    Returns a new (H, W) bool mask; every change moves a pixel by at most the band from the
    original outline. Without regions, or with ``params.enabled`` false, a copy of ``mask``.

    Where the band is wider than ``WORK_BAND_PX`` (images wider than ~1500 px) GrabCut runs
    on the window scaled down until the band is that wide, and its outline is scaled back
    up; the band is then enforced at full resolution.
    """
    out = mask.copy()
    if not params.enabled or not mask.any():
        return out
    band = int(round(scale_px(params.band_px, width_px)))
    scale = min(1.0, WORK_BAND_PX / band)
    work_band = max(1, int(round(band * scale)))
    h, w = mask.shape
    margin = 2 * band + MIN_RING_PX  # the band, then a ring for the background model
    for y0, y1, x0, x1 in _windows(mask, margin):
        region = mask[y0:y1, x0:x1].astype(np.uint8)
        roi = np.ascontiguousarray(image[y0:y1, x0:x1])
        if scale < 1.0:
            drawn = _grabcut_scaled(roi, region, band, work_band, scale, params)
        else:
            drawn = _grabcut(roi, region, _disc(band), params)
        if drawn is None:
            continue
        window = out[y0:y1, x0:x1]
        inside = region > 0
        window[inside] = drawn[inside]
        window[~inside & drawn] = True
    return out


def _windows(mask: np.ndarray, margin: int) -> list[tuple[int, int, int, int]]:
    """(y0, y1, x0, x1) windows, one per group of regions less than 2 ``margin`` apart: each
    group's bounding box grown by ``margin``. Regions whose windows would overlap share one
    GrabCut (and its colour models): no pixel is cut twice."""
    grown = mask_box(mask, margin)
    if grown is None:
        return []
    top, left = grown[0].start, grown[1].start
    box = mask[grown].astype(np.uint8)
    square = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
    n, _, stats, _ = cv2.connectedComponentsWithStats(cv2.dilate(box, square), connectivity=8)
    return [
        (int(y) + top, int(y + bh) + top, int(x) + left, int(x + bw) + left)
        for x, y, bw, bh in stats[1:n, :4]
    ]


def _disc(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _grabcut_scaled(
    roi: np.ndarray,
    region: np.ndarray,
    band: int,
    work_band: int,
    scale: float,
    params: RefineParams,
) -> np.ndarray | None:
    """:func:`_grabcut` on the window scaled by ``scale`` (its band ``work_band`` px), the
    outline scaled back (bilinear, then halved) and kept within ``band`` px of ``region``."""
    h, w = region.shape
    size = (max(2, round(w * scale)), max(2, round(h * scale)))
    small_roi = cv2.resize(roi, size, interpolation=cv2.INTER_AREA)
    small_region = cv2.resize(region * np.uint8(255), size, interpolation=cv2.INTER_AREA) >= 128
    drawn = _grabcut(small_roi, small_region.astype(np.uint8), _disc(work_band), params)
    if drawn is None:
        return None
    up = cv2.resize(drawn.astype(np.uint8) * np.uint8(255), (w, h), interpolation=cv2.INTER_LINEAR)
    disc = _disc(band)
    return ((up >= 128) | (cv2.erode(region, disc) > 0)) & (cv2.dilate(region, disc) > 0)


def _grabcut(
    roi: np.ndarray, region: np.ndarray, disc: np.ndarray, params: RefineParams
) -> np.ndarray | None:
    """GrabCut of one region in its window: (h, w) bool, or None when OpenCV gives up (a
    window with too few pixels of one side to fit its colour model)."""
    trimap = np.full(region.shape, cv2.GC_BGD, np.uint8)
    trimap[cv2.dilate(region, disc) > 0] = cv2.GC_PR_BGD
    trimap[region > 0] = cv2.GC_PR_FGD
    trimap[cv2.erode(region, disc) > 0] = cv2.GC_FGD
    if not (trimap == cv2.GC_PR_FGD).any() and not (trimap == cv2.GC_FGD).any():
        return None  # scaled down to nothing
    bg = np.zeros((1, 65), np.float64)
    fg = np.zeros((1, 65), np.float64)
    # GrabCut seeds its colour models with k-means++ from OpenCV's thread-local RNG: reseed
    # it so that a view gives the same mask every time (reruns, resumed runs, any worker)
    cv2.setRNGSeed(RNG_SEED)
    try:
        # the rectangle is ignored with GC_INIT_WITH_MASK
        cv2.grabCut(roi, trimap, (0, 0, 0, 0), bg, fg, params.iterations, cv2.GC_INIT_WITH_MASK)
    except cv2.error:
        return None
    return (trimap == cv2.GC_FGD) | (trimap == cv2.GC_PR_FGD)
