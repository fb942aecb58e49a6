"""How far in front of the old surface each changed region stands (not in the paper; issue 17).

A region's 3D position (:mod:`streetcd.detect.regions`) is read from the *old* surface behind
it: for something added, that is the wall or the ground behind the new thing, metres from
where it stands. A car parked since the scan, its cabin seen against a façade, is then
located on the façade, and the change objects built from it cannot tell it stands on the
road. The neighbours tell where it stands: sampled at the depth of the thing itself, they
show what the view shows; sampled at the old surface behind it, they do not.

For each region ``r`` and each fraction ``f`` of ``fractions`` (1 = the old surface), the
region's pixels ``p`` are sampled in every neighbour ``q`` at ``p``'s ray point at depth
``f · z_p`` (:func:`streetcd.detect.correlate.warp_neighbour`, both images histogram-stretched
and averaged over a ``window_px`` square, as in :mod:`streetcd.detect.sweep`)::

    D_p(f)  = max_q d(I_p, I_q(f))            over the neighbours that see the point (≥ 1)
    cost(f) = median_p D_p(f)                  over the region's pixels with D_p(f) defined
    f*      = argmin_f cost(f)                 (a parabola through its two neighbours)

with ``d`` the colour distance of :func:`~streetcd.detect.correlate.color_distance` in [0, 1]
and ``z_p`` metres. One neighbour is enough (the nearer-depth test wants two, pixel by
pixel): the median over a region's hundreds of pixels decides, and at a street's end only
one neighbour sees a near thing at its own depth.

``f*`` is the region's depth fraction when its cost is lower than the old surface's by at
least ``min_gain`` and ``min_pixels`` pixels gave it; otherwise NaN: the old surface explains
the region as well (a change *on* the surface: paint, a removed object's background), or too
few pixels were seen. The point where the region stands is then ``C + f* · (X − C)`` for its
centroid ``X`` on the old surface and the camera centre ``C`` (a point on a ray at a fraction
of its depth). Computed at ``scale`` of the view's resolution, never wider than
``max_work_px``, on at most ``max_samples`` pixels a region (evenly spread).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from streetcd.detect.correlate import Neighbour, NeighbourView, camera_rays, stretch_lut
from streetcd.detect.sweep import packed, worst_difference
from streetcd.types import Intrinsics, Pose


@dataclass(frozen=True)
class Working:
    """The view and its neighbours at the working size (:func:`working_set`): ``view``
    (h, w, 3) float32 stretched and window-averaged colours, ``depth`` (h, w) float32 metres
    of the old surface, ``intrinsics`` at that size, ``neighbours`` likewise prepared
    (:func:`_small`)."""

    view: np.ndarray
    depth: np.ndarray
    intrinsics: Intrinsics
    neighbours: tuple[Neighbour, ...]


def working_set(
    image_p: np.ndarray,
    depth_p: np.ndarray,
    intrinsics_p: Intrinsics,
    neighbours: Sequence[NeighbourView],
    *,
    window_px: int,
    scale: float,
    max_work_px: int,
    percentiles: tuple[float, float] = (1.0, 99.0),
) -> Working | None:
    """The view ``image_p`` (H, W, 3) uint8 with its old surface ``depth_p`` (H, W) float32
    and its ``neighbours`` (image, depth, intrinsics, pose, holes) shrunk by a whole factor
    ``k``, the least at which they are at most ``scale`` of the view's resolution and
    ``max_work_px`` wide (a whole factor: OpenCV's area average takes a quarter of the time
    there, 31 → 8.5 ms for a 12 MP image); None without a neighbour."""
    if not neighbours:
        return None
    h, w = depth_p.shape
    k = max(1, math.ceil(max(1.0 / float(scale), w / max_work_px) - 1e-9))
    s = 1.0 / k
    size = (max(1, round(w * s)), max(1, round(h * s)))
    return Working(
        _smoothed(image_p, size, window_px, percentiles),
        cv2.resize(depth_p, size, interpolation=cv2.INTER_NEAREST),
        intrinsics_p.scaled(size[0] / w),
        tuple(_small(nb, s, window_px, percentiles) for nb in neighbours),
    )


def region_depth_fractions(
    working: Working,
    labels: np.ndarray,
    n_regions: int,
    pose_p: Pose,
    *,
    fractions: Sequence[float],
    min_gain: float,
    min_pixels: int,
    max_samples: int,
    occlusion_tolerance_m: float,
) -> np.ndarray:
    """``f*`` of the module docstring for regions ``1 … n_regions`` of ``labels`` (H, W)
    int32 (0 = none), at full size; ``working`` from :func:`working_set`, ``pose_p`` the
    view's pose in the neighbours' local frame. fractions : increasing depth fractions in
    (0, 1], ending at 1. Returns (n_regions,) float64: the depth fraction in (0, 1], NaN
    without evidence."""
    out = np.full(n_regions, np.nan)
    fr = np.asarray(fractions, np.float64)
    costs = region_costs(
        working,
        labels,
        n_regions,
        pose_p,
        fractions=fr,
        min_pixels=min_pixels,
        max_samples=max_samples,
        occlusion_tolerance_m=occlusion_tolerance_m,
    )
    at_old = costs[:, -1]
    for r in range(n_regions):
        c = costs[r]
        if not np.isfinite(c).any() or not np.isfinite(at_old[r]):
            continue
        j = int(np.nanargmin(c))
        if at_old[r] - c[j] >= min_gain:
            out[r] = _refined(fr, c, j)
    return out


def region_costs(
    working: Working,
    labels: np.ndarray,
    n_regions: int,
    pose_p: Pose,
    *,
    fractions: np.ndarray,
    min_pixels: int,
    max_samples: int,
    occlusion_tolerance_m: float,
) -> np.ndarray:
    """(n_regions, len(fractions)) ``cost(f)`` of the module docstring (NaN: fewer than
    ``min_pixels`` pixels seen by a neighbour)."""
    costs = np.full((n_regions, fractions.size), np.nan)
    h, w = working.depth.shape
    labels_s = cv2.resize(labels, (w, h), interpolation=cv2.INTER_NEAREST)
    picks, owners = _samples(labels_s, working.depth, n_regions, max_samples, min_pixels)
    if picks.size == 0:
        return costs
    rays = packed(camera_rays(working.intrinsics), picks)
    colours = packed(working.view, picks)
    depth = packed(working.depth, picks)
    n = picks.size
    d = np.empty((fractions.size, n), np.float32)
    for j, f in enumerate(fractions):
        at_f = depth * np.float32(f)
        d[j] = worst_difference(
            colours, working.neighbours, at_f, rays, pose_p, occlusion_tolerance_m, min_seen=1
        ).ravel()[:n]
    bounds = np.searchsorted(owners, np.arange(n_regions + 1))
    for r in range(n_regions):
        block = d[:, bounds[r] : bounds[r + 1]]
        if block.shape[1] < min_pixels:
            continue
        enough = np.isfinite(block).sum(axis=1) >= min_pixels
        if enough.any():
            with np.errstate(all="ignore"):
                costs[r, enough] = np.nanmedian(block[enough], axis=1)
    return costs


def _smoothed(
    image: np.ndarray, size: tuple[int, int], window_px: int, percentiles: tuple[float, float]
) -> np.ndarray:
    """``image`` (H, W, 3) uint8 shrunk to ``size`` (w, h), histogram-stretched on its own
    (eq. 5's balancing, its percentiles read from the shrunk image) and averaged over a
    ``window_px`` square: float32."""
    small = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    lut = stretch_lut(small, percentiles, sample_step=2)
    return cv2.blur(cv2.LUT(small, lut), (int(window_px), int(window_px)))


def _small(
    nb: NeighbourView, scale: float, window_px: int, percentiles: tuple[float, float]
) -> Neighbour:
    """A neighbour at ``scale`` of its resolution, prepared as the view (:func:`_smoothed`);
    its depth nearest-pixel, holes left open (nothing hides a point there)."""
    image, depth, intrinsics, pose, _ = nb
    h, w = depth.shape
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    return Neighbour(
        _smoothed(image, size, window_px, percentiles),
        cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST),
        intrinsics.scaled(size[0] / w),
        pose,
    )


def _samples(
    labels: np.ndarray, depth: np.ndarray, n_regions: int, max_samples: int, min_pixels: int
) -> tuple[np.ndarray, np.ndarray]:
    """Flat indices of at most ``max_samples`` pixels a region with an old surface (evenly
    spread; none for a region of fewer than ``min_pixels`` such pixels), and the region
    (0-based) each belongs to."""
    flat = labels.ravel()
    has = np.isfinite(depth.ravel()) & (flat > 0)
    idx = np.flatnonzero(has)
    owner = flat[idx] - 1
    order = np.argsort(owner, kind="stable")
    idx, owner = idx[order], owner[order]
    counts = np.bincount(owner, minlength=n_regions)
    keep = []
    start = 0
    for c in counts:
        if c >= min_pixels:  # a smaller region gets no depth: not worth its samples
            step = max(1, -(-int(c) // max_samples))
            keep.append(np.arange(start, start + c, step))
        start += c
    take = np.concatenate(keep) if keep else np.zeros(0, np.int64)
    return idx[take], owner[take]


def _refined(fractions: np.ndarray, cost: np.ndarray, j: int) -> float:
    """The minimum of the parabola through the cost at ``j`` and its two neighbours (where
    both are defined and the spacing even; ``j`` being the least, it lies within half a step
    of ``fractions[j]``); else ``fractions[j]``."""
    if 0 < j < fractions.size - 1 and np.isfinite(cost[j - 1 : j + 2]).all():
        a, b, c = cost[j - 1], cost[j], cost[j + 1]
        den = a - 2 * b + c
        step = fractions[j + 1] - fractions[j]
        if den > 0 and np.isclose(fractions[j] - fractions[j - 1], step):
            return float(fractions[j] + 0.5 * step * (a - c) / den)
    return float(fractions[j])
