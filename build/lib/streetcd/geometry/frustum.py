"""A view's frustum, range-limited and buffered: which points it keeps and which ground boxes
(tiles, files) it can see. The pure half of the crop (:mod:`streetcd.store.crop` reads the
points).

The frustum of a view, in its camera frame (OpenCV axes, z forward), is the pyramid bounded by
the rays through the image border: normalised coordinates ``x0 ≤ x/z ≤ x1``, ``y0 ≤ y/z ≤ y1``
(the undistorted border's bounding box, so distortion never cuts points off). A point is kept
when its signed distance to each of the four side planes is ≤ ``buffer_m`` and its range
``|X − C|`` is ≤ ``max_range_m + buffer_m``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numba
import numpy as np

from streetcd.geometry.camera import pixel_rays
from streetcd.types import Intrinsics, View


def frustum_bounds(intrinsics: Intrinsics, samples: int = 16) -> np.ndarray:
    """(x0, x1, y0, y1) float64: bounding box of the image border in normalised (undistorted)
    camera coordinates; pixel border at −0.5 and W − 0.5 (OpenCV centres)."""
    w, h = intrinsics.width, intrinsics.height
    t = np.linspace(0.0, 1.0, samples)
    us, vs = -0.5 + t * w, -0.5 + t * h
    border = np.concatenate(
        [
            np.column_stack([us, np.full_like(us, -0.5)]),
            np.column_stack([us, np.full_like(us, h - 0.5)]),
            np.column_stack([np.full_like(vs, -0.5), vs]),
            np.column_stack([np.full_like(vs, w - 0.5), vs]),
        ]
    )
    rays = pixel_rays(border, intrinsics)
    return np.array([rays[:, 0].min(), rays[:, 0].max(), rays[:, 1].min(), rays[:, 1].max()])


def in_frustum(
    points: np.ndarray,
    view: View,
    max_range_m: float = 60.0,
    buffer_m: float = 1.0,
    bounds: np.ndarray | None = None,
) -> np.ndarray:
    """(N,) bool: points (N, 3) float64 metres, in the frame of ``view``'s pose, inside the
    view frustum grown by ``buffer_m`` and within ``max_range_m + buffer_m`` of the camera.
    ``bounds`` is :func:`frustum_bounds` of the view's intrinsics when already known.

    In camera coordinates (x, y, z) = R X + t, the signed distance to the side plane through
    the border ray x/z = a is (x − a z)/√(1 + a²) (right, bottom) or (a z − x)/√(1 + a²)
    (left, top); each must be ≤ buffer_m, and |(x, y, z)| ≤ max_range_m + buffer_m.
    """
    x0, x1, y0, y1 = frustum_bounds(view.intrinsics) if bounds is None else bounds
    b = buffer_m
    limits = np.array(
        [
            x0,
            x1,
            y0,
            y1,
            b * np.hypot(1.0, x0),
            b * np.hypot(1.0, x1),
            b * np.hypot(1.0, y0),
            b * np.hypot(1.0, y1),
            (max_range_m + b) ** 2,
        ]
    )
    pts = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    return _frustum_mask(pts, view.pose.R, view.pose.t, limits)


@numba.njit(cache=True, nogil=True)
def _frustum_mask(
    points: np.ndarray, R: np.ndarray, t: np.ndarray, limits: np.ndarray
) -> np.ndarray:
    """One fused pass of :func:`in_frustum` (a crop tests millions of points per view)."""
    x0, x1, y0, y1, bx0, bx1, by0, by1, r2 = limits
    out = np.empty(points.shape[0], dtype=np.bool_)
    for k in range(points.shape[0]):
        px, py, pz = points[k, 0], points[k, 1], points[k, 2]
        x = R[0, 0] * px + R[0, 1] * py + R[0, 2] * pz + t[0]
        y = R[1, 0] * px + R[1, 1] * py + R[1, 2] * pz + t[1]
        z = R[2, 0] * px + R[2, 1] * py + R[2, 2] * pz + t[2]
        out[k] = (
            (x - x1 * z) <= bx1
            and (x0 * z - x) <= bx0
            and (y - y1 * z) <= by1
            and (y0 * z - y) <= by0
            and x * x + y * y + z * z <= r2
        )
    return out


def frustum_hull(view: View, max_range_m: float, buffer_m: float) -> np.ndarray:
    """(8, 3) float64 corners, in the frame of ``view``'s pose, of a polytope that contains
    every point :func:`in_frustum` keeps: the four grown side planes between the depth where
    they cross behind the camera and depth ``max_range_m + buffer_m``."""
    x0, x1, y0, y1 = frustum_bounds(view.intrinsics)
    b = buffer_m
    sx0, sx1, sy0, sy1 = (b * np.hypot(1.0, a) for a in (x0, x1, y0, y1))
    # From x0 z − sx0 ≤ x ≤ x1 z + sx1: z ≥ −(sx0 + sx1) / (x1 − x0); same for y.
    z_lo = max(-(sx0 + sx1) / (x1 - x0), -(sy0 + sy1) / (y1 - y0))
    z_hi = max_range_m + b
    corners = []
    for z in (z_lo, z_hi):
        for x in (x0 * z - sx0, x1 * z + sx1):
            for y in (y0 * z - sy0, y1 * z + sy1):
                corners.append((x, y, z))
    cam = np.array(corners)
    return (cam - view.pose.t) @ view.pose.R  # camera → world: Rᵀ (x − t)


def convex_hull_2d(points: np.ndarray) -> np.ndarray:
    """(K, 2) counter-clockwise convex hull of (N, 2) points (Andrew's monotone chain)."""
    pts = sorted(map(tuple, np.asarray(points, dtype=np.float64)))
    if len(pts) <= 2:
        return np.array(pts)

    def half(seq: list[tuple[float, float]]) -> list[tuple[float, float]]:
        out: list[tuple[float, float]] = []
        for p in seq:
            while (
                len(out) >= 2
                and (
                    (out[-1][0] - out[-2][0]) * (p[1] - out[-2][1])
                    - (out[-1][1] - out[-2][1]) * (p[0] - out[-2][0])
                )
                <= 0
            ):
                out.pop()
            out.append(p)
        return out

    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1])


def polygon_meets_boxes(poly: np.ndarray, boxes: np.ndarray) -> np.ndarray:
    """(M,) bool: convex polygon (K, 2) overlaps axis-aligned boxes (M, 4) minx, miny, maxx,
    maxy — separating-axis test on the box axes and the polygon's edge normals."""
    lo, hi = poly.min(axis=0), poly.max(axis=0)
    hit = (
        (boxes[:, 0] <= hi[0])
        & (boxes[:, 2] >= lo[0])
        & (boxes[:, 1] <= hi[1])
        & (boxes[:, 3] >= lo[1])
    )
    corners = np.stack(
        [boxes[:, [0, 1]], boxes[:, [2, 1]], boxes[:, [2, 3]], boxes[:, [0, 3]]], axis=1
    )  # (M, 4, 2)
    for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        normal = np.array([b[1] - a[1], a[0] - b[0]])  # outward for a counter-clockwise hull
        if not normal.any():
            continue
        # Separated if every box corner lies beyond this edge.
        beyond = ((corners - a) @ normal) > 0
        hit &= ~beyond.all(axis=1)
    return hit


def view_footprint(view: View, max_range_m: float, buffer_m: float) -> np.ndarray:
    """(K, 2) ground polygon (view's pose frame, x/y) that every kept point lies over."""
    return convex_hull_2d(frustum_hull(view, max_range_m, buffer_m)[:, :2])


def boxes_seen(
    view: View, origin: np.ndarray, boxes: np.ndarray, max_range_m: float, buffer_m: float
) -> np.ndarray:
    """(M,) bool: which boxes (M, 4) CRS minx, miny, maxx, maxy may hold points ``view``
    (pose in the CRS) keeps: they meet its ground footprint and its range circle's box."""
    local = view.local(origin)
    poly = view_footprint(local, max_range_m, buffer_m) + origin[:2]
    c, r = view.center[:2], max_range_m + buffer_m
    near = np.all(np.maximum(boxes[:, :2] - c, c - boxes[:, 2:]) <= r, axis=1)
    return near & polygon_meets_boxes(poly, boxes)


def lookup_box(
    view: View, origin: np.ndarray, max_range_m: float, buffer_m: float
) -> tuple[float, float, float, float]:
    """CRS box of the view's ground footprint clipped to its range (for the index lookup)."""
    poly = view_footprint(view.local(origin), max_range_m, buffer_m) + origin[:2]
    c, r = view.center[:2], max_range_m + buffer_m
    lo, hi = np.maximum(poly.min(axis=0), c - r), np.minimum(poly.max(axis=0), c + r)
    return float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])


def union_mask(
    points: np.ndarray,
    views: Sequence[View],
    origin: np.ndarray,
    max_range_m: float,
    buffer_m: float,
) -> np.ndarray:
    """(N,) bool: points (N, 3) local to ``origin`` inside the frustum of any of ``views``."""
    keep = np.zeros(len(points), dtype=bool)
    for view in views:
        local = view.local(origin)
        keep |= in_frustum(points, local, max_range_m, buffer_m, frustum_bounds(view.intrinsics))
    return keep
