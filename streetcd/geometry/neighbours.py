"""Overlapping neighbours of a view, by frustum overlap (paper §4: 70–80 % in-strip overlap,
2–3 neighbours per view).

The overlap of ``q`` with ``p`` is the share of sample rays of ``p`` (a coarse pixel grid at a
few depths, i.e. points filling ``p``'s frustum) that ``q`` sees: in front of ``q`` and inside
its image. No cloud is needed, so neighbours can be planned before any tile is read.
"""

from __future__ import annotations

from collections.abc import Sequence

import numba
import numpy as np

from streetcd.config import CorrelateParams, scale_px
from streetcd.geometry.camera import pixel_rays
from streetcd.types import Intrinsics, View

DEPTHS_M = (5.0, 10.0, 20.0, 40.0)  # street objects lie 10–30 m away (paper §4)
GRID = 12  # sample rays per image side
PARALLAX_DEPTH_M = 20.0  # the parallax of a neighbour is judged at this depth (10–30 m above)
MIN_PARALLAX_PX = CorrelateParams.min_parallax_px  # px at REFERENCE_WIDTH_PX (the config's)
BLOCK_VIEWS = 128  # views projected per kernel call when planning (~2 MB of samples)


def camera_samples(
    intrinsics: Intrinsics, depths_m: Sequence[float] = DEPTHS_M, grid: int = GRID
) -> np.ndarray:
    """(grid² · len(depths_m), 3) float64 points filling a camera's frustum, in the camera's
    own frame (metres): a ``grid`` × ``grid`` lattice of pixel rays at each depth."""
    u = (np.arange(grid) + 0.5) * intrinsics.width / grid - 0.5
    v = (np.arange(grid) + 0.5) * intrinsics.height / grid - 0.5
    uu, vv = np.meshgrid(u, v)
    uv = np.column_stack([uu.ravel(), vv.ravel()])
    uv_all = np.tile(uv, (len(depths_m), 1))
    depth = np.repeat(np.asarray(depths_m, dtype=np.float64), len(uv))
    return pixel_rays(uv_all, intrinsics) * depth[:, None]


def frustum_samples(
    view: View, depths_m: Sequence[float] = DEPTHS_M, grid: int = GRID
) -> np.ndarray:
    """(grid² · len(depths_m), 3) float64 points filling ``view``'s frustum, in the frame of
    ``view.pose`` (pass a view already moved to a local frame): :func:`camera_samples`
    moved by ``X = Rᵀ (x_cam − t)`` (:func:`streetcd.geometry.camera.backproject`)."""
    cam = camera_samples(view.intrinsics, depths_m, grid)
    return (cam - view.pose.t) @ view.pose.R


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
    """(len(others),) float64: :func:`overlap` of ``view`` with each of ``others``."""
    return overlaps_many([view], [others], depths_m, grid)[0]


def overlaps_many(
    views: Sequence[View],
    others_of: Sequence[Sequence[View]],
    depths_m: Sequence[float] = DEPTHS_M,
    grid: int = GRID,
    block: int = BLOCK_VIEWS,
) -> list[np.ndarray]:
    """:func:`overlaps` of each ``views[i]`` with its ``others_of[i]``: a list of
    (len(others_of[i]),) float64 arrays.

    Batched projections, ``block`` views at a time: the frustum samples of every view into
    all of its candidates in one call of a compiled kernel (:func:`_seen_counts`). Planning
    a city calls this for every view: one numpy call per view spent its time in numpy's
    per-call overhead (10 s of a 10,000-view plan), and batched numpy calls in their
    temporaries (3.5 s; docs/BENCHMARKS.md).
    """
    out: list[np.ndarray] = []
    cam_samples: dict[Intrinsics, np.ndarray] = {}  # rays × depths in a camera's own frame
    for start in range(0, len(views), block):
        part = range(start, min(start + block, len(views)))
        out += _overlap_block(
            [views[i] for i in part], [others_of[i] for i in part], depths_m, grid, cam_samples
        )
    return out


def _overlap_block(
    views: Sequence[View],
    others_of: Sequence[Sequence[View]],
    depths_m: Sequence[float],
    grid: int,
    cam_samples: dict[Intrinsics, np.ndarray],
) -> list[np.ndarray]:
    """:func:`overlaps_many` of one block: candidate lists padded to the longest (padding
    masked out), each view's frustum samples in a frame at its own centre."""
    counts = [len(o) for o in others_of]
    k = max(counts, default=0)
    if k == 0:
        return [np.zeros(0, dtype=np.float64) for _ in views]
    b = len(views)
    pad = [list(o) + [views[i]] * (k - len(o)) for i, o in enumerate(others_of)]
    flat = [o for row in pad for o in row]
    for v in views:
        if v.intrinsics not in cam_samples:
            cam_samples[v.intrinsics] = camera_samples(v.intrinsics, depths_m, grid)
    # Each view's samples in a frame at its own centre (t = 0 there): X = Rᵀ x_cam, (B, N, 3).
    pts = np.stack([cam_samples[v.intrinsics] @ v.pose.R for v in views])
    R = np.stack([o.pose.R for o in flat]).reshape(b, k, 3, 3)
    centres = np.stack([v.center for v in views])
    offset = np.stack([o.center for o in flat]).reshape(b, k, 3) - centres[:, None, :]
    t = np.matmul(-R, offset[..., None])[..., 0]  # (B, K, 3): each candidate's t, local
    cams = np.array(
        [[o.intrinsics.fx, o.intrinsics.fy, o.intrinsics.cx, o.intrinsics.cy] for o in flat]
    ).reshape(b, k, 4)
    size = np.array([[o.intrinsics.width, o.intrinsics.height] for o in flat], dtype=np.float64)
    dist = np.array([o.intrinsics.dist for o in flat], dtype=np.float64).reshape(b, k, 5)
    seen = _seen_counts(pts, np.ascontiguousarray(R), t, cams, size.reshape(b, k, 2), dist)
    shares = seen / pts.shape[1]  # (B, K)
    return [shares[i, :c].copy() for i, c in enumerate(counts)]


@numba.njit(cache=True, nogil=True)
def _seen_counts(
    pts: np.ndarray,
    R: np.ndarray,
    t: np.ndarray,
    cams: np.ndarray,
    size: np.ndarray,
    dist: np.ndarray,
) -> np.ndarray:
    """(B, K) int64: how many of view b's samples ``pts[b]`` ((B, N, 3) metres, in a frame at
    its centre) candidate k sees: ``x_cam = R[b, k] X + t[b, k]`` in front (z > 0) and its
    pixel ``u = fx x' + cx``, ``v = fy y' + cy`` inside the image (``size[b, k]`` = W, H;
    pixel border at −0.5 and W − 0.5), with ``(x', y')`` the normalised coordinates
    distorted by ``dist[b, k]`` (k1, k2, p1, p2, k3; :func:`streetcd.geometry.camera.distort`).

    One fused pass: the numpy version made a dozen (B, N, K) temporaries and took 3.5 s of a
    10,000-view plan (docs/BENCHMARKS.md)."""
    nb, n_samples, nk = pts.shape[0], pts.shape[1], R.shape[1]
    out = np.zeros((nb, nk), dtype=np.int64)
    for b in range(nb):
        for k in range(nk):
            r = R[b, k]
            fx, fy, cx, cy = cams[b, k, 0], cams[b, k, 1], cams[b, k, 2], cams[b, k, 3]
            w, h = size[b, k, 0], size[b, k, 1]
            k1, k2, p1, p2, k3 = (
                dist[b, k, 0],
                dist[b, k, 1],
                dist[b, k, 2],
                dist[b, k, 3],
                dist[b, k, 4],
            )
            distorted = k1 != 0.0 or k2 != 0.0 or p1 != 0.0 or p2 != 0.0 or k3 != 0.0
            count = 0
            for n in range(n_samples):
                px, py, pz = pts[b, n, 0], pts[b, n, 1], pts[b, n, 2]
                z = r[2, 0] * px + r[2, 1] * py + r[2, 2] * pz + t[b, k, 2]
                if not z > 0.0:
                    continue
                xn = (r[0, 0] * px + r[0, 1] * py + r[0, 2] * pz + t[b, k, 0]) / z
                yn = (r[1, 0] * px + r[1, 1] * py + r[1, 2] * pz + t[b, k, 1]) / z
                if distorted:
                    r2 = xn * xn + yn * yn
                    radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
                    xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
                    yn = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
                    xn = xd
                u = fx * xn + cx
                v = fy * yn + cy
                if u >= -0.5 and u < w - 0.5 and v >= -0.5 and v < h - 0.5:
                    count += 1
            out[b, k] = count
    return out


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
    return select_neighbours_many(
        [view],
        [candidates],
        n,
        max_distance_m=max_distance_m,
        depths_m=depths_m,
        min_parallax_px=min_parallax_px,
    )[0]


def select_neighbours_many(
    views: Sequence[View],
    candidates_of: Sequence[Sequence[View]],
    n: int = 3,
    *,
    max_distance_m: float = 2 * DEPTHS_M[-1],
    depths_m: Sequence[float] = DEPTHS_M,
    min_parallax_px: float = MIN_PARALLAX_PX,
) -> list[list[View]]:
    """:func:`select_neighbours` of each ``views[i]`` among its ``candidates_of[i]``, the
    overlaps of all of them batched (:func:`overlaps_many`)."""
    near_of: list[list[View]] = []
    dists_of: list[np.ndarray] = []
    for view, candidates in zip(views, candidates_of, strict=True):
        cands = [c for c in candidates if c.name != view.name]
        if cands:
            dists = np.linalg.norm(np.stack([c.center for c in cands]) - view.center, axis=1)
        else:
            dists = np.zeros(0)
        keep = np.flatnonzero(dists <= max_distance_m)
        near_of.append([cands[i] for i in keep])
        dists_of.append(dists[keep])
    shares_of = overlaps_many(views, near_of, depths_m)
    out = []
    for view, near, dists, shares in zip(views, near_of, dists_of, shares_of, strict=True):
        shares = shares * _parallax_weights(view, dists, min_parallax_px)
        scored = [
            (-round(float(share), 9), float(dist), cand.name, cand)
            for share, dist, cand in zip(shares, dists, near, strict=True)
            if share > 0
        ]
        scored.sort(key=lambda s: s[:3])
        out.append([s[3] for s in scored[:n]])
    return out


def _parallax_weights(
    view: View, dists_m: Sequence[float] | np.ndarray, min_parallax_px: float
) -> np.ndarray:
    """(len(dists_m),) in [0, 1]: ``min(1, parallax / min_parallax_px)`` of
    :func:`select_neighbours` for candidates at ``dists_m`` metres from ``view``."""
    dists = np.asarray(dists_m, dtype=np.float64)
    if min_parallax_px <= 0:
        return np.ones(len(dists))
    intr = view.intrinsics
    focal = 0.5 * (intr.fx + intr.fy)
    parallax = focal * dists / PARALLAX_DEPTH_M
    return np.minimum(1.0, parallax / scale_px(min_parallax_px, intr.width, minimum=0.0))
