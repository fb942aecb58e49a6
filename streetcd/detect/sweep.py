"""Nearer-depth test: does a depth in front of the old surface explain the view and its
neighbours better than the old surface does? (not in the paper; issue 16).

Eq. 5 sees an *added* object only through the colour difference between the object in the
view and what the neighbours show through the old surface behind it. Where the object's
colour is close to that background (a grey pole before a pale façade), the raw change stays
below the S-curve's middle and the object is missed, while the evidence that something stands
in front is in the neighbours all along: sampled at the object's own depth, every neighbour
shows the same colours the view does.

For each pixel ``p`` with an old surface at camera depth ``z`` and each fraction ``f_k`` of
``fractions``, the neighbours ``q`` are sampled at ``p``'s ray point at depth ``f_k · z``
(:func:`streetcd.detect.correlate.warp_neighbour`; a point in front of the old surface is
never occluded in ``q`` by it) and compared with the view, both locally averaged over a
``window_px`` square (colour distance of :func:`~streetcd.detect.correlate.color_distance`,
each image histogram-stretched on its own, eq. 5's balancing)::

    D(f)   = max_q d(I_p, I_q(f))          over the neighbours that see the point (≥ 2)
    D_near = min_{f_k < 1} D(f_k)
    N_p    = clip((D(1) − D_near − margin) / span, 0, 1)    where D_near ≤ match, else 0

The nearer depth has to *explain* the pixel (``D_near`` ≤ ``match``), not only do better
than the old surface: beside an added object, where one neighbour sees the object through the
old surface (its ghost), some nearer depth often lands both neighbours on similar colours by
chance, but seldom on the same ones. One depth has to fit every neighbour at once: the neighbours before and after the view along
the street shift opposite ways with depth, so a registration error of the view, which moves
the pixel the same way in all of them, is not explained away by a nearer depth (the margin
takes what is left). So the test asks for that: it gives no evidence when no two of the
neighbours' baselines from the view point more than 90° apart (:func:`opposite_baselines`), as
at the first and last view of a walk, where every neighbour lies behind or ahead and a pose
error shifts them all alike (docs/TUNING.md, thirty-fourth round). Pixels no two neighbours
see, and pixels without an old surface, give no evidence. Computed at ``scale`` of the view's
resolution, never wider than ``max_work_px``.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from streetcd.detect.correlate import (
    Neighbour,
    NeighbourView,
    camera_rays,
    color_distance,
    stretch_histogram,
    warp_neighbour,
)
from streetcd.types import Intrinsics, Pose


def nearer_depth_change(
    image_p: np.ndarray,
    depth_p: np.ndarray,
    intrinsics_p: Intrinsics,
    pose_p: Pose,
    neighbours: Sequence[NeighbourView],
    *,
    fractions: Sequence[float],
    margin: float,
    span: float,
    match: float,
    window_px: int,
    scale: float,
    max_work_px: int,
    occlusion_tolerance_m: float,
    percentiles: tuple[float, float] = (1.0, 99.0),
) -> np.ndarray:
    """``N_p`` of the module docstring for view ``p``: (H, W) float32 in [0, 1].

    image_p : (H, W, 3) uint8 RGB. depth_p : (H, W) float32 metres, camera z of the old
    surface (NaN = none). neighbours : (image (h, w, 3) uint8 RGB, depth (h, w) float32,
    intrinsics, pose, holes) per neighbour, poses in the local frame of ``pose_p``.
    fractions : depth fractions in (0, 1) tried in front of the old surface.
    """
    h, w = depth_p.shape
    if not opposite_baselines(pose_p, [nb[3] for nb in neighbours]):
        return np.zeros((h, w), np.float32)
    s = min(float(scale), max_work_px / w)
    small = (max(1, round(w * s)), max(1, round(h * s)))
    intr_s = intrinsics_p.scaled(small[0] / w)
    depth_s = cv2.resize(depth_p, small, interpolation=cv2.INTER_NEAREST)
    out = np.zeros(depth_s.shape, np.float32)
    if len(neighbours) < 2 or not np.isfinite(depth_s).any():
        return np.zeros((h, w), np.float32)
    rays = camera_rays(intr_s)
    k = (int(window_px), int(window_px))
    stretched = np.asarray(stretch_histogram(image_p, percentiles), np.float32)
    view = cv2.blur(cv2.resize(stretched, small, interpolation=cv2.INTER_AREA), k)
    nbs = [
        Neighbour(
            cv2.blur(np.asarray(stretch_histogram(img, percentiles), np.float32), k),
            dep,
            intr,
            pose,
            holes=holes,
        )
        for img, dep, intr, pose, holes in neighbours
    ]
    at_old = worst_difference(view, nbs, depth_s, rays, pose_p, occlusion_tolerance_m)
    # Only a pixel the old surface explains worse than the margin can gain: the nearer
    # depths are tried on those alone, packed into rows (about a third of a street view's
    # pixels; the result is the same as on the whole raster).
    todo = np.flatnonzero(np.nan_to_num(at_old, nan=0.0).ravel() > margin)
    if todo.size == 0:
        return np.zeros((h, w), np.float32)
    depth_t, rays_t, view_t = (packed(a, todo) for a in (depth_s, rays, view))
    best_near = np.full(depth_t.shape, np.inf, np.float32)
    for f in fractions:
        nearer = depth_t * np.float32(f)
        d = worst_difference(view_t, nbs, nearer, rays_t, pose_p, occlusion_tolerance_m)
        np.fmin(best_near, d, out=best_near)
    best = best_near.ravel()[: todo.size]
    gain = at_old.ravel()[todo] - best
    ok = np.isfinite(gain) & (best <= match)
    out.ravel()[todo[ok]] = np.clip((gain[ok] - margin) / span, 0.0, 1.0)
    return cv2.resize(out, (w, h), interpolation=cv2.INTER_LINEAR)


def opposite_baselines(pose_p: Pose, poses: Sequence[Pose]) -> bool:
    """Whether two of the baselines from the view's centre to the neighbours' (``poses``)
    point more than 90° apart (a negative dot product): neighbours on both sides of the view,
    whose images a depth in front of the old surface shifts opposite ways."""
    base = [np.asarray(q.center - pose_p.center, np.float64) for q in poses]
    return any(float(a @ b) < 0 for i, a in enumerate(base) for b in base[i + 1 :])


def worst_difference(
    view: np.ndarray,
    neighbours: Sequence[Neighbour],
    depth: np.ndarray,
    rays: np.ndarray,
    pose_p: Pose,
    occlusion_tolerance_m: float,
    min_seen: int = 2,
) -> np.ndarray:
    """(H, W) float32: the largest colour distance between ``view`` and the neighbours
    sampled at ``depth`` along ``rays``, over the neighbours that see the point; NaN where
    fewer than ``min_seen`` do (or no depth)."""
    worst = np.zeros(depth.shape, np.float32)
    seen = np.zeros(depth.shape, np.uint8)
    for nb in neighbours:
        warped, valid = warp_neighbour(nb, depth, rays, pose_p, occlusion_tolerance_m)
        d = color_distance(view, warped)
        np.maximum(worst, d, out=worst, where=valid)
        seen += valid
    worst[seen < min_seen] = np.nan
    return worst


PACK_WIDTH = 4096  # OpenCV's remap takes rasters under 32,767 pixels a side


def packed(a: np.ndarray, index: np.ndarray) -> np.ndarray:
    """The pixels ``index`` (flat, into the first two axes) of ``a`` (H, W[, C]) as a raster of
    ``PACK_WIDTH`` columns (the last row padded with NaN or zeros): (R, PACK_WIDTH[, C])."""
    flat = a.reshape(-1, *a.shape[2:])[index]
    rows = -(-len(index) // PACK_WIDTH)
    fill = np.nan if np.issubdtype(a.dtype, np.floating) else 0
    out = np.full((rows * PACK_WIDTH, *a.shape[2:]), fill, a.dtype)
    out[: len(index)] = flat
    return out.reshape(rows, PACK_WIDTH, *a.shape[2:])
