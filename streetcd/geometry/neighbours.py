"""Overlapping neighbours of a view, by frustum overlap (paper §4: 70–80 % in-strip overlap,
2–3 neighbours per view).

The overlap of ``q`` with ``p`` is the share of sample rays of ``p`` (a coarse pixel grid at a
few depths, i.e. points filling ``p``'s frustum) that ``q`` sees: in front of ``q`` and inside
its image. No cloud is needed, so neighbours can be planned before any tile is read.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from streetcd.config import CorrelateParams, scale_px
from streetcd.geometry.camera import backproject, distort
from streetcd.types import View

DEPTHS_M = (5.0, 10.0, 20.0, 40.0)  # street objects lie 10–30 m away (paper §4)
GRID = 12  # sample rays per image side
PARALLAX_DEPTH_M = 20.0  # the parallax of a neighbour is judged at this depth (10–30 m above)
MIN_PARALLAX_PX = CorrelateParams.min_parallax_px  # px at REFERENCE_WIDTH_PX (the config's)


def frustum_samples(
    view: View, depths_m: Sequence[float] = DEPTHS_M, grid: int = GRID
) -> np.ndarray:
    """(grid² · len(depths_m), 3) float64 points filling ``view``'s frustum, in the frame of
    ``view.pose`` (pass a view already moved to a local frame)."""
    intr = view.intrinsics
    u = (np.arange(grid) + 0.5) * intr.width / grid - 0.5
    v = (np.arange(grid) + 0.5) * intr.height / grid - 0.5
    uu, vv = np.meshgrid(u, v)
    uv = np.column_stack([uu.ravel(), vv.ravel()])
    uv_all = np.tile(uv, (len(depths_m), 1))
    depth = np.repeat(np.asarray(depths_m, dtype=np.float64), len(uv))
    return backproject(uv_all, depth, intr, view.pose)


def overlap(
    view: View, other: View, depths_m: Sequence[float] = DEPTHS_M, grid: int = GRID
) -> float:
    """Share in [0, 1] of ``view``'s frustum samples that ``other`` sees (in front, in image).

    Both views in the same frame (CRS is fine: computed relative to ``view``'s centre).
    """
    return float(overlaps(view, [other], depths_m, grid)[0])


def overlaps(
    view: View, others: Sequence[View], depths_m: Sequence[float] = DEPTHS_M, grid: int = GRID
) -> np.ndarray:
    """(len(others),) float64: :func:`overlap` of ``view`` with each of ``others``.

    One batched projection of ``view``'s samples into every other camera: planning a city
    calls this once per view, and the per-pair version spent its time in numpy call overhead
    (samples rebuilt and projected 576 points at a time, ~12 times per view).
    """
    if not others:
        return np.zeros(0, dtype=np.float64)
    origin = view.center
    pts = frustum_samples(view.local(origin), depths_m, grid)  # (N, 3) metres, local
    R = np.stack([o.pose.R for o in others])  # (Q, 3, 3)
    t = np.stack([o.pose.shifted(origin).t for o in others])  # (Q, 3)
    pc = np.matmul(pts, R.transpose(0, 2, 1)) + t[:, None, :]  # (Q, N, 3) camera frames
    depth = pc[..., 2]
    ahead = depth > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        xn = np.where(ahead, pc[..., 0] / depth, np.nan)
        yn = np.where(ahead, pc[..., 1] / depth, np.nan)
    for k, o in enumerate(others):  # rare in practice: most pipelines undistort first
        if o.intrinsics.has_distortion:
            xn[k], yn[k] = distort(xn[k], yn[k], o.intrinsics.dist)
    intr = np.array(
        [[o.intrinsics.fx, o.intrinsics.fy, o.intrinsics.cx, o.intrinsics.cy] for o in others]
    )
    size = np.array([[o.intrinsics.width, o.intrinsics.height] for o in others], dtype=np.float64)
    u = intr[:, 0:1] * xn + intr[:, 2:3]
    v = intr[:, 1:2] * yn + intr[:, 3:4]
    with np.errstate(invalid="ignore"):  # NaN (behind the camera) compares False
        inside = (u >= -0.5) & (u < size[:, 0:1] - 0.5) & (v >= -0.5) & (v < size[:, 1:2] - 0.5)
    return np.mean(ahead & inside, axis=1)


def select_neighbours(
    view: View,
    candidates: Sequence[View],
    n: int = 3,
    *,
    max_distance_m: float = 2 * DEPTHS_M[-1],
    depths_m: Sequence[float] = DEPTHS_M,
    min_parallax_px: float = MIN_PARALLAX_PX,
) -> list[View]:
    """The ``n`` candidates with the best overlap and parallax (score > 0).

    A candidate's score is its frustum overlap with ``view`` (:func:`overlaps`) times
    ``min(1, parallax / min_parallax_px)``, where ``parallax = f · b / PARALLAX_DEPTH_M`` px is
    how far a point at the street's typical depth moves between the two images (``f`` the
    view's focal length in px, ``b`` the distance between the centres, m). Without parallax
    every pixel is photo-consistent whatever the depth (eq. 4 warps it onto itself): a camera
    that did not move (a car at a light, the same camera a second later) overlaps best and
    proves nothing, so it scores 0 and is never chosen. ``min_parallax_px`` is given at
    :data:`streetcd.config.REFERENCE_WIDTH_PX` and scaled with the view's width; 0 ranks by
    overlap alone (the paper's choice).

    ``view`` itself (same name) is never chosen; candidates farther than ``max_distance_m``
    are skipped unseen. Ties are broken by the distance between the centres, then by name,
    so the choice is deterministic.
    """
    near, dists = [], []
    for cand in candidates:
        if cand.name == view.name:
            continue
        dist = float(np.linalg.norm(cand.center - view.center))
        if dist <= max_distance_m:
            near.append(cand)
            dists.append(dist)
    shares = overlaps(view, near, depths_m) * _parallax_weights(view, dists, min_parallax_px)
    scored = [
        (-round(float(share), 9), dist, cand.name, cand)
        for share, dist, cand in zip(shares, dists, near, strict=True)
        if share > 0
    ]
    scored.sort(key=lambda s: s[:3])
    return [s[3] for s in scored[:n]]


def _parallax_weights(view: View, dists_m: Sequence[float], min_parallax_px: float) -> np.ndarray:
    """(len(dists_m),) in [0, 1]: ``min(1, parallax / min_parallax_px)`` of
    :func:`select_neighbours` for candidates at ``dists_m`` metres from ``view``."""
    dists = np.asarray(dists_m, dtype=np.float64)
    if min_parallax_px <= 0:
        return np.ones(len(dists))
    intr = view.intrinsics
    focal = 0.5 * (intr.fx + intr.fy)
    parallax = focal * dists / PARALLAX_DEPTH_M
    return np.minimum(1.0, parallax / scale_px(min_parallax_px, intr.width, minimum=0.0))
