"""The unscanned side of near objects: a second depth hypothesis next to their silhouettes.

**Not in the paper.** A mobile laser scanner drives on the road; a street camera walks the
sidewalk. A street-light pole at the kerb, a metre or two from the camera, was scanned on its
road side only, and the half-cylinder the scanner saw, seen from the camera, covers only part
of the pole's width: the z-buffer has no point there, so the view's old surface is the wall
ten metres behind. Eq. 5 then compares the image (pole) with the neighbours sampled through
the wall's depth (wall) and calls the unscanned half of every near pole a change (seen as
the largest false detections on the synthetic streets, docs/TUNING.md).

The fix is a second depth hypothesis where such a gap can be: each pixel whose old surface is
farther than ``min_gap_m`` behind a surface within ``reach = f · margin_m / z_near`` pixels
(``margin_m`` metres at that surface's depth) is also tested at that nearer depth. The raw
change there is the smaller of the two (eq. 5's own rule: one consistent explanation is
enough); where no neighbour sees the nearer point, nothing can tell the two apart and the
pixel gives no evidence, like a pixel that no neighbour sees (the near pole's case: a
neighbour six metres along the street does not see a point 1.5 m in front of the view).
The reach shrinks with distance, so only what is near the camera gets a band of any width.

**The band ends at the near object's outline in the image** (our addition, issue 16, with
``edge_threshold``). The unscanned side of a near object is part of that object in the view:
it continues the scanned side's image region up to the object's outline. A pixel beyond an
image edge from the near surface shows something else (a new thin pole standing a hand's
width beside a near column, whose reach covers it): the hypothesis is kept only where a
path from the near surface's own blocks reaches without crossing an edge of the view
(OpenCV's Canny on its grey levels), so that a change there keeps the evidence eq. 5 gives
it. Within an object's outline (no edge between its two sides) the band is what it was.

Every nearer surface makes the hypothesis, the ground and the road included, though they
have no hidden side: leaving them out raised the false-positive rate from 15–25 % to 22–34 %
and cost 0.03 to 0.06 kappa on the synthetic streets, the true positives unchanged
(docs/TUNING.md): near the camera the band around the near ground is where the neighbours'
views of the street do not overlap.
"""

from __future__ import annotations

import cv2
import numba
import numpy as np

from streetcd import classes

# roles whose band is their reach alone when the bands end at outlines: the ground has no
# unscanned side, and its band is where the neighbours' views do not overlap near the camera
GROUND_ROLES = (classes.GROUND, classes.ROAD)
WORK_STEP_PX = 4  # the near-depth raster is built on blocks of at least this many pixels ...
WORK_WIDTH_PX = 480  # ... and of at most this many blocks across (12 MP: 8 px blocks)


def near_depth_hypothesis(
    depth: np.ndarray,
    focal_px: float,
    margin_m: float,
    min_gap_m: float,
    grey: np.ndarray | None = None,
    edge_threshold: float = 0.0,
    bounded: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W) float32 metres: the nearest depth within each pixel's reach of a nearer surface,
    NaN where there is none, it is not nearer by ``min_gap_m``, or the pixel has no
    surface itself.

    depth : (H, W) float32 metres, camera z of the old surface, NaN = none. focal_px :
    focal length in pixels of that raster. A surface at depth z reaches ``focal_px ·
    margin_m / z`` px around itself (a grey erosion with that radius per depth band; bands of
    a factor 2 in depth, each eroded at the band's nearest depth, so a reach is at most twice
    too long). Computed on blocks (block minimum; ``WORK_STEP_PX`` wide, or wider so that at
    most ``WORK_WIDTH_PX`` blocks span the image) and read back nearest.

    grey : (H, W) uint8 grey levels of the view, with ``edge_threshold`` > 0 (Canny's upper
    threshold; the lower is half of it): the band of the surface pixels in ``bounded`` ((H,
    W) bool; None: all) is kept only where it is reached from that surface without crossing
    an edge of ``grey`` (:func:`_within_outline`, see the module doc); the other surfaces'
    bands (the ground's: it has no hidden side) are the reach alone. None or 0: every band
    is the reach alone.
    """
    h, w = depth.shape
    k = max(WORK_STEP_PX, -(-w // WORK_WIDTH_PX))
    if grey is None or edge_threshold <= 0:
        near, _ = _reach(_block_min(depth, k), focal_px, margin_m, k)
    else:
        if grey.shape != depth.shape or (bounded is not None and bounded.shape != depth.shape):
            raise ValueError(f"grey and bounded must have the depth's shape {depth.shape}")
        inside = np.ones(depth.shape, np.bool_) if bounded is None else bounded
        own, rest = _block_min_split(depth, inside, k)
        near, steps = _reach(own, focal_px, margin_m, k)
        if steps > 0:
            near = _within_outline(near, own, grey, k, edge_threshold, min_gap_m, steps)
        if bounded is not None:
            np.minimum(near, _reach(rest, focal_px, margin_m, k)[0], out=near)
    out = np.empty((h, w), np.float32)
    _read_back(depth, near, k, np.float32(min_gap_m), out)
    return out


def _reach(blocks: np.ndarray, focal_px: float, margin_m: float, k: int) -> tuple[np.ndarray, int]:
    """The nearest depth within reach of each block (+inf: none) and the widest reach, in
    blocks, of ``blocks`` ((h, w) float32 block minima, +inf = no surface)."""
    near = np.full(blocks.shape, np.inf, np.float32)
    # bands [z0, 2 z0): reaches under one block are what the surface already covers
    z0 = float(np.nanmin(blocks)) if np.isfinite(blocks).any() else np.inf
    widest = int(focal_px * margin_m / z0 / k) if np.isfinite(z0) else 0
    while np.isfinite(z0):
        reach = int(focal_px * margin_m / z0 / k)
        if reach < 1:
            break
        band = np.where((blocks >= z0) & (blocks < 2 * z0), blocks, np.inf).astype(np.float32)
        kernel = np.ones((2 * reach + 1, 2 * reach + 1), np.uint8)
        np.minimum(near, cv2.erode(band, kernel, borderType=cv2.BORDER_REPLICATE), out=near)
        z0 *= 2
    return near, widest


@numba.njit(cache=True, nogil=True)
def _block_min(depth, k):  # pragma: no cover - compiled
    """(ceil(H/k), ceil(W/k)) float32 minimum of each k × k block, +inf for no surface."""
    h, w = depth.shape
    out = np.full(((h + k - 1) // k, (w + k - 1) // k), np.inf, np.float32)
    for r in range(h):
        row = out[r // k]
        for b in range(row.shape[0]):
            m = row[b]
            for c in range(b * k, min(b * k + k, w)):
                z = depth[r, c]
                if z < m:  # NaN compares False
                    m = z
            row[b] = m
    return out


@numba.njit(cache=True, nogil=True)
def _block_min_split(depth, inside, k):  # pragma: no cover - compiled
    """:func:`_block_min` of the pixels where ``inside`` (H, W) bool holds, and of the others."""
    h, w = depth.shape
    shape = ((h + k - 1) // k, (w + k - 1) // k)
    own = np.full(shape, np.inf, np.float32)
    rest = np.full(shape, np.inf, np.float32)
    for r in range(h):
        own_row, rest_row = own[r // k], rest[r // k]
        for b in range(shape[1]):
            mo, mr = own_row[b], rest_row[b]
            for c in range(b * k, min(b * k + k, w)):
                z = depth[r, c]
                if not z < np.inf:  # NaN: no surface
                    continue
                i = inside[r, c]
                mo = min(mo, z if i else np.inf)
                mr = min(mr, np.inf if i else z)
            own_row[b], rest_row[b] = mo, mr
    return own, rest


@numba.njit(cache=True, nogil=True)
def _read_back(depth, near, k, min_gap, out):  # pragma: no cover - compiled
    """out = the block's near depth where the pixel's own surface is at least ``min_gap``
    behind it, else NaN; pixels without a surface stay without (they give eq. 5 no evidence
    either way)."""
    h, w = depth.shape
    for r in range(h):
        row = near[r // k]
        for b in range(row.shape[0]):
            z = row[b]
            for c in range(b * k, min(b * k + k, w)):
                out[r, c] = z if depth[r, c] >= z + min_gap else np.nan


def _within_outline(
    near: np.ndarray,
    blocks: np.ndarray,
    grey: np.ndarray,
    k: int,
    edge_threshold: float,
    min_gap_m: float,
    steps: int,
) -> np.ndarray:
    """``near`` (blocks, +inf = none) kept where the near surface reaches it within its outline.

    Every block without a Canny edge of ``grey`` ((H, W) uint8) passes on the nearest depth
    it holds (``blocks``) or has been passed to its 4-neighbours, one block a step, for at
    most ``steps`` steps (the widest reach in blocks); a block holding an edge neither passes
    nor takes one (an edge one pixel wide closes its whole block). A block keeps its
    hypothesis where a depth within ``min_gap_m`` of it has reached it: the near surface
    itself, from inside the outline that holds both. A near object so thin that all its
    blocks hold edges keeps no band (letting such blocks pass their own depth on was tried
    on one full-size street's views only, where it changed nothing; not kept).
    """
    edges = cv2.Canny(grey, edge_threshold / 2, edge_threshold)
    closed = _block_max(edges, k) > 0
    reached = np.where(closed, np.float32(np.inf), blocks).astype(np.float32)
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    for _ in range(steps):
        grown: np.ndarray = cv2.erode(reached, cross, borderType=cv2.BORDER_REPLICATE)
        grown[closed] = np.inf
        np.minimum(grown, reached, out=grown)
        if np.array_equal(grown, reached):
            break
        reached = grown
    return np.where(reached <= near + np.float32(min_gap_m), near, np.float32(np.inf)).astype(
        np.float32
    )


@numba.njit(cache=True, nogil=True)
def _block_max(a, k):  # pragma: no cover - compiled
    """(ceil(H/k), ceil(W/k)) maximum of each k × k block of ``a`` (H, W) uint8."""
    h, w = a.shape
    out = np.zeros(((h + k - 1) // k, (w + k - 1) // k), a.dtype)
    for r in range(h):
        row = out[r // k]
        for b in range(row.shape[0]):
            m = row[b]
            for c in range(b * k, min(b * k + k, w)):
                if a[r, c] > m:
                    m = a[r, c]
            row[b] = m
    return out
