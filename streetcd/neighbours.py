"""Overlapping neighbours of a view, by frustum overlap (paper §4: 70–80 % in-strip overlap,
2–3 neighbours per view).

The overlap of ``q`` with ``p`` is the share of sample rays of ``p`` (a coarse pixel grid at a
few depths, i.e. points filling ``p``'s frustum) that ``q`` sees: in front of ``q`` and inside
its image. No cloud is needed, so neighbours can be planned before any tile is read.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from streetcd.camera import backproject, in_image, project
from streetcd.views import View

DEPTHS_M = (5.0, 10.0, 20.0, 40.0)  # street objects lie 10–30 m away (paper §4)
GRID = 12  # sample rays per image side


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
    origin = view.center
    p, q = view.local(origin), other.local(origin)
    pts = frustum_samples(p, depths_m, grid)
    uv, depth = project(pts, q.intrinsics, q.pose)
    return float(np.mean((depth > 0) & in_image(uv, q.intrinsics)))


def select_neighbours(
    view: View,
    candidates: Sequence[View],
    n: int = 3,
    *,
    max_distance_m: float = 2 * DEPTHS_M[-1],
    depths_m: Sequence[float] = DEPTHS_M,
) -> list[View]:
    """The ``n`` candidates whose frustum overlaps ``view``'s most (overlap > 0).

    ``view`` itself (same name) is never chosen; candidates farther than ``max_distance_m``
    are skipped unseen. Ties are broken by the distance between the centres, then by name,
    so the choice is deterministic.
    """
    scored = []
    for cand in candidates:
        if cand.name == view.name:
            continue
        dist = float(np.linalg.norm(cand.center - view.center))
        if dist > max_distance_m:
            continue
        share = overlap(view, cand, depths_m)
        if share > 0:
            scored.append((-round(share, 9), dist, cand.name, cand))
    scored.sort(key=lambda s: s[:3])
    return [s[3] for s in scored[:n]]
