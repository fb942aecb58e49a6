"""The view-dependent surface: a 2D triangulation of the z-buffered points and the per-pixel
depth and class rasters it gives (paper §3.3, first paragraph).

Triangulation. The paper triangulates the projected points with a 2D Delaunay triangulation and
drops triangles whose vertices differ in depth by more than 0.5 m (they span a depth
discontinuity) or that have an edge longer than 30 px (wrong connections between separate
surfaces). A general Delaunay is slow at street-view sizes (scipy/qhull: docs/BENCHMARKS.md),
so :func:`triangulate` builds the triangulation as the dual of a *discrete Voronoi diagram on
a cell grid*: each occupied cell is a seed, a distance transform labels every cell with its
nearest seed, the labels are corrected with the points' true positions, and wherever three
or four labels meet in a 2 × 2 block of cells their points form one triangle, or two split
along the Delaunay diagonal. Where every cell holds a point this is the
grid triangulation (two triangles per quad); where points are sparser than the grid the
Voronoi dual still connects them, as Delaunay would. With ``cell_px = w`` (the z-buffer's
block window) each BWZB cell holds at most one point, so no point is lost and the grid is w²
times smaller than the image.

It is a close approximation of Delaunay, not Delaunay: Voronoi edges shorter than a cell are
missed, so some near-cocircular quads get the other diagonal, and rarely two triangles
overlap (the rasteriser keeps the nearer one). It leaves no holes inside the point set. On a
synthetic street the filtered surface covers nearly the same pixels as Delaunay's, in a
small fraction of scipy's time (docs/BENCHMARKS.md; ``benchmarks/surface_choices.py`` reproduces
it). Points outside the image take no part, so a rim of up to ``w / 2`` px along the image
border has no surface.

Rasters. Depth is interpolated barycentrically in *inverse* depth (linear in the image for a
plane seen by a pinhole camera, the disparity the paper interpolates), so planes come out
exact. The class of a pixel is the class of the nearest vertex of the triangle covering it (the
nearest kept point in all but degenerate cases); pixels outside every kept triangle have no
surface: depth NaN, class 0, valid False. Overlapping triangles resolve to the nearest surface.

Near objects' points (not in the paper; issue 16). A pole 1-3 m from the camera is scanned in
profiles tens of pixels apart, wider than any triangle the filters keep; the surface in its
outline was then the wall behind it. :func:`fill_from_points` closes the near points of poles,
signs and furniture into their own surface after the triangles
(``SurfaceParams.point_fill_classes``; docs/DECISIONS.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import cv2
import numba
import numpy as np

from streetcd.config import DetectParams, SurfaceParams, ZBufferParams, scale_px
from streetcd.detect.spacing import class_spacing
from streetcd.detect.zbuffer import (
    ProjectedPoints,
    _block_cells,
    _check_points,
    project_cloud,
    weighted_zbuffer,
)
from streetcd.errors import EmptyViewError, InputError
from streetcd.types import Intrinsics, Pose


@dataclass(frozen=True)
class ViewSurface:
    """Per-pixel surface of a view.

    depth : (H, W) float32, metres, camera-frame z; NaN where there is no surface.
    classes : (H, W) uint8, class code of the nearest point; 0 where there is no surface.
    valid : (H, W) bool, True where a kept triangle covers the pixel centre.
    colour : (H, W, 3) uint8 RGB of the nearest point (the reference cloud's own colours,
        8-bit), 0 where there is no surface; None when the cloud has no colours.
    """

    depth: np.ndarray
    classes: np.ndarray
    valid: np.ndarray
    colour: np.ndarray | None = None


# --- triangulation -------------------------------------------------------------------------


@numba.njit(cache=True, nogil=True)
def _dual_triangles(labels, seeds, uv, depth, lim):  # pragma: no cover - compiled
    """Triangles where 3–4 Voronoi labels meet in a 2 × 2 block, filtered (see module doc).

    labels : (gh, gw) int32, 1-based seed label per cell; seeds : (S,) int64 point per label.
    lim : the filters' limits, see :func:`_emit`.
    Returns (T, 3) int32 point indices, each row sorted ascending (duplicates possible).
    """
    gh, gw = labels.shape
    out = np.empty((2 * max(gh - 1, 0) * max(gw - 1, 0), 3), dtype=np.int32)
    n = 0
    quad = np.empty(4, dtype=np.int64)
    uniq = np.empty(4, dtype=np.int64)
    for r in range(gh - 1):
        for c in range(gw - 1):
            quad[0] = labels[r, c]  # cyclic order: TL, TR, BR, BL
            quad[1] = labels[r, c + 1]
            quad[2] = labels[r + 1, c + 1]
            quad[3] = labels[r + 1, c]
            k = 0
            for j in range(4):
                new = True
                for m in range(k):
                    if uniq[m] == quad[j]:
                        new = False
                if new:
                    uniq[k] = quad[j]
                    k += 1
            if k < 3:
                continue
            if k == 3:
                n = _emit(
                    out,
                    n,
                    seeds[uniq[0] - 1],
                    seeds[uniq[1] - 1],
                    seeds[uniq[2] - 1],
                    uv,
                    depth,
                    lim,
                )
                continue
            p0 = seeds[quad[0] - 1]
            p1 = seeds[quad[1] - 1]
            p2 = seeds[quad[2] - 1]
            p3 = seeds[quad[3] - 1]
            # Split along the Delaunay diagonal (p3 outside the circle through p0, p1, p2)
            # unless that folds a non-convex quad.
            a02 = _area2(uv, p0, p1, p2) * _area2(uv, p0, p2, p3) > 0.0
            a13 = _area2(uv, p0, p1, p3) * _area2(uv, p1, p2, p3) > 0.0
            use02 = _incircle(uv, p0, p1, p2, p3) <= 0.0
            if (use02 and a02) or not a13:
                n = _emit(out, n, p0, p1, p2, uv, depth, lim)
                n = _emit(out, n, p0, p2, p3, uv, depth, lim)
            else:
                n = _emit(out, n, p0, p1, p3, uv, depth, lim)
                n = _emit(out, n, p1, p2, p3, uv, depth, lim)
    return out[:n]


@numba.njit(cache=True, inline="always")
def _area2(uv, a, b, c):  # pragma: no cover - compiled
    return (uv[b, 0] - uv[a, 0]) * (uv[c, 1] - uv[a, 1]) - (uv[b, 1] - uv[a, 1]) * (
        uv[c, 0] - uv[a, 0]
    )


@numba.njit(cache=True)
def _incircle(uv, a, b, c, d):  # pragma: no cover - compiled
    """> 0 when d lies inside the circle through a, b, c (any orientation of a, b, c)."""
    adx, ady = uv[a, 0] - uv[d, 0], uv[a, 1] - uv[d, 1]
    bdx, bdy = uv[b, 0] - uv[d, 0], uv[b, 1] - uv[d, 1]
    cdx, cdy = uv[c, 0] - uv[d, 0], uv[c, 1] - uv[d, 1]
    det = (
        (adx * adx + ady * ady) * (bdx * cdy - cdx * bdy)
        - (bdx * bdx + bdy * bdy) * (adx * cdy - cdx * ady)
        + (cdx * cdx + cdy * cdy) * (adx * bdy - bdx * ady)
    )
    return det if _area2(uv, a, b, c) > 0.0 else -det


@numba.njit(cache=True)
def _refine_labels(labels, seeds, uv, cell):  # pragma: no cover - compiled
    """Relabel each cell with the nearest (true position) seed among its 3 × 3 neighbourhood.

    The distance transform sees seeds at their cell centres; this moves the Voronoi borders
    to where the points really are. Seed cells keep their own label so no point is lost.
    """
    gh, gw = labels.shape
    out = labels.copy()
    centre = 0.5 * (cell - 1)
    for r in range(gh):
        v = r * cell + centre
        for c in range(gw):
            own = labels[r, c]
            p = seeds[own - 1]
            if (
                int(math.floor(uv[p, 0] + 0.5)) // cell == c
                and int(math.floor(uv[p, 1] + 0.5)) // cell == r
            ):
                continue  # a seed cell
            u = c * cell + centre
            best = (uv[p, 0] - u) ** 2 + (uv[p, 1] - v) ** 2
            for rr in range(max(r - 1, 0), min(r + 2, gh)):
                for cc in range(max(c - 1, 0), min(c + 2, gw)):
                    lab = labels[rr, cc]
                    if lab == own:
                        continue
                    q = seeds[lab - 1]
                    d = (uv[q, 0] - u) ** 2 + (uv[q, 1] - v) ** 2
                    if d < best:
                        best = d
                        out[r, c] = lab
    return out


@numba.njit(cache=True, inline="always")
def _dist2(uv, a, b):  # pragma: no cover - compiled
    du = uv[a, 0] - uv[b, 0]
    dv = uv[a, 1] - uv[b, 1]
    return du * du + dv * dv


@numba.njit(cache=True)
def _emit(out, n, a, b, c, uv, depth, lim):  # pragma: no cover - compiled
    """Append triangle (a, b, c) sorted if it passes the depth-jump, edge and area filters.

    lim : (max_jump m, max_edge² px², jump_pt (N,) m, edge_pt (N,) px, role_pt (N,) uint8):
    a triangle may span max(max_jump, the least jump_pt of its vertices) in depth and have
    edges up to max(max_edge, the largest edge_pt of its vertices), the latter only when its
    vertices share one role_pt; (0,) arrays: the scalars alone, any roles.
    """
    max_jump, max_edge2, jump_pt, edge_pt, role_pt = lim
    if jump_pt.shape[0] > 0:  # the densest vertex decides: objects stay apart from sparse ground
        max_jump = max(max_jump, min(jump_pt[a], jump_pt[b], jump_pt[c]))
    widen = edge_pt.shape[0] > 0 and min(edge_pt[a], edge_pt[b], edge_pt[c]) > 0.0
    if widen and role_pt.shape[0] > 0:  # one surface's gaps, not a step between two
        widen = role_pt[a] == role_pt[b] and role_pt[b] == role_pt[c]
    if widen:
        # the sparsest vertex decides (its spacing must be bridged), and only where every
        # vertex may widen (0: a vertex near the camera or of a role kept to the fixed limit)
        e = max(edge_pt[a], edge_pt[b], edge_pt[c])
        max_edge2 = max(max_edge2, e * e)
    za, zb, zc = depth[a], depth[b], depth[c]
    if max(za, zb, zc) - min(za, zb, zc) > max_jump:
        return n
    if _dist2(uv, a, b) > max_edge2 or _dist2(uv, b, c) > max_edge2 or _dist2(uv, a, c) > max_edge2:
        return n
    if abs(_area2(uv, a, b, c)) < 1e-9:
        return n
    if a > b:
        a, b = b, a
    if b > c:
        b, c = c, b
    if a > b:
        a, b = b, a
    out[n, 0] = a
    out[n, 1] = b
    out[n, 2] = c
    return n + 1


@numba.njit(cache=True, nogil=True)
def _unique_rows(tris):  # pragma: no cover - compiled
    """(T, 3) int32 rows → the distinct rows in first-seen order (an open-addressing hash set).

    Keeping the emission order keeps the triangles in image scan order, which the rasteriser's
    memory access likes.
    """
    n = tris.shape[0]
    size = 1
    while size < 2 * n:
        size *= 2
    table = np.full(size, -1, dtype=np.int64)
    keep = np.zeros(n, dtype=np.bool_)
    for t in range(n):
        a, b, c = np.int64(tris[t, 0]), np.int64(tris[t, 1]), np.int64(tris[t, 2])
        h = ((a * 73856093) ^ (b * 19349663) ^ (c * 83492791)) & (size - 1)
        while True:
            s = table[h]
            if s < 0:
                table[h] = t
                keep[t] = True
                break
            if tris[s, 0] == a and tris[s, 1] == b and tris[s, 2] == c:
                break
            h = (h + 1) & (size - 1)
    return tris[keep]


def _triangulate(
    uv: np.ndarray,
    depth: np.ndarray,
    shape: tuple[int, int],
    image_width: int,
    params: SurfaceParams,
    cell_px: int,
    spacing: tuple[np.ndarray, float] | None = None,
    classes: np.ndarray | None = None,
) -> np.ndarray:
    h, w = shape
    cells = _block_cells(uv, depth, h, w, cell_px)
    gh, gw = (h + cell_px - 1) // cell_px, (w + cell_px - 1) // cell_px
    seeds = cells[cells >= 0]  # row-major order = the label order of OpenCV's distance transform
    if seeds.shape[0] < 3 or gh < 2 or gw < 2:
        return np.empty((0, 3), dtype=np.int32)
    empty = (cells < 0).astype(np.uint8).reshape(gh, gw)
    _, labels = cv2.distanceTransformWithLabels(
        empty, cv2.DIST_L2, cv2.DIST_MASK_5, labelType=cv2.DIST_LABEL_PIXEL
    )
    labels = _refine_labels(labels, seeds, uv, cell_px)
    # The paper's 30 px is for 16 MP images; scaled down to a small image it can fall below
    # the spacing the block z-buffer leaves (one point per w-cell), and the surface falls
    # apart. Never filter edges shorter than EDGE_FLOOR_CELLS grid cells.
    max_edge = max(scale_px(params.max_edge_px, image_width), EDGE_FLOOR_CELLS * cell_px)
    jump_pt, edge_pt = _spacing_limits(depth, params, spacing, classes)
    role_pt = np.empty(0, np.uint8)
    if params.spacing_edge_same_role and classes is not None and edge_pt.shape[0] > 0:
        role_pt = np.ascontiguousarray(classes, np.uint8)
    lim = (float(params.max_depth_jump_m), float(max_edge * max_edge), jump_pt, edge_pt, role_pt)
    return _unique_rows(_dual_triangles(labels, seeds, uv, depth, lim))


def _spacing_limits(
    depth: np.ndarray,
    params: SurfaceParams,
    spacing: tuple[np.ndarray, float] | None,
    classes: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Per-point limits from the cloud's own spacing (:mod:`streetcd.detect.spacing`):
    ``spacing_jump_factor`` · s_i metres and ``spacing_edge_factor`` · f · s_i / z_i px, each
    (N,) float64, or (0,) when its factor is 0 or ``spacing`` (s (N,) m, f px) is None.

    The edge limit is 0 (no widening: a triangle with such a vertex keeps the fixed limit) at
    points nearer than ``spacing_edge_min_depth_m``, at points whose spacing is below
    ``spacing_edge_min_spacing_m`` or above ``spacing_edge_max_spacing_m`` (when > 0) and,
    when ``spacing_edge_classes`` is set, at points of other roles (``classes`` (N,) uint8;
    None: every point may widen)."""
    none = np.empty(0, np.float64)
    if spacing is None:
        return none, none
    s, focal_px = spacing
    jump, edge = none, none
    if params.spacing_jump_factor > 0:
        jump = np.ascontiguousarray(params.spacing_jump_factor * s, np.float64)
    if params.spacing_edge_factor > 0:
        edge = np.ascontiguousarray(params.spacing_edge_factor * focal_px * s / depth, np.float64)
        # near the camera the widened limit grows as 1/z (hundreds of px at 3 m on a sparse
        # LiDAR) and bridges the ground that the recording vehicle's own body hides
        edge[depth < params.spacing_edge_min_depth_m] = 0.0
        # a class as dense as mobile mapping keeps the configured limit (it suits it)
        edge[s < params.spacing_edge_min_spacing_m] = 0.0
        # ... or, the other way round, a sparse class does (its long edges bridge real gaps)
        if params.spacing_edge_max_spacing_m > 0:
            edge[s > params.spacing_edge_max_spacing_m] = 0.0
        if params.spacing_edge_classes and classes is not None:
            roles = np.asarray(params.spacing_edge_classes, dtype=np.uint8)
            edge[~np.isin(classes, roles)] = 0.0
    return jump, edge


EDGE_FLOOR_CELLS = 3  # see _grid_triangles


def triangulate(
    uv: np.ndarray,
    depth: np.ndarray,
    image_width: int,
    params: SurfaceParams,
    *,
    cell_px: int = 1,
) -> np.ndarray:
    """View-dependent triangulation with the depth-jump and edge-length filters (paper §3.3).

    Parameters
    ----------
    uv : (N, 2) float64, pixels (u column, v row), OpenCV convention.
    depth : (N,) float64, metres, camera-frame z.
    image_width : W in pixels; the edge threshold ``params.max_edge_px`` is scaled to it.
    params : ``max_depth_jump_m`` (max − min vertex depth allowed), ``max_edge_px``.
    cell_px : the grid cell (see module docstring). Of several points in one cell only the
        nearest becomes a vertex; pass the z-buffer window w for z-buffered points, 1 for
        arbitrary ones.

    Returns
    -------
    (T, 3) int32, indices into ``uv`` of the kept triangles, each row ascending, rows unique,
    in image scan order.
    Points outside ``[-0.5, image_width - 0.5)`` horizontally or above the image are ignored.
    """
    uv, depth = _check_points(uv, depth)
    if int(cell_px) < 1:
        raise InputError(f"cell_px must be >= 1, got {cell_px}")
    finite = np.isfinite(uv[:, 1])
    height = int(math.floor(uv[finite, 1].max() + 0.5)) + 1 if finite.any() else 1
    return _triangulate(
        uv, depth, (max(height, 1), int(image_width)), int(image_width), params, int(cell_px)
    )


# --- rasters -------------------------------------------------------------------------------


@numba.njit(cache=True, inline="always")
def _span(k_u, inv_k_u, k_0, lo, hi):  # pragma: no cover - compiled
    """Narrow [lo, hi] to the columns where k_0 + k_u · col >= −1e-9 (``inv_k_u`` = 1 / k_u,
    taken once per triangle: a division per row was a sixth of the rasteriser's time)."""
    if k_u > 0.0:
        lo = max(lo, (-1e-9 - k_0) * inv_k_u)
    elif k_u < 0.0:
        hi = min(hi, (-1e-9 - k_0) * inv_k_u)
    elif k_0 < -1e-9:
        hi = lo - 1.0
    return lo, hi


@numba.njit(cache=True, inline="always")
def _inverse(x):  # pragma: no cover - compiled
    return 1.0 / x if x != 0.0 else 0.0


@numba.njit(cache=True, nogil=True)
def _rasterise(uv, depth, tris, height, width, classes, colours):  # pragma: no cover
    """Barycentric inverse-depth rasterisation with a z-test; (H, W) float32 depth (NaN
    where no triangle covers the pixel), and the class (H, W) uint8 and colour (H, W, 3)
    uint8 of each pixel's nearest vertex (0 where none; colours (N, 3) uint8, or (0, 3)
    for none: the colour raster is then (0, 0, 3)).

    Everything evaluated per pixel is an affine function of (column, row) over a triangle:
    the barycentric weights, the inverse depth and the differences of squared distances to
    the vertices; each is stepped by one addition per pixel. Class and colour are written
    with the depth, not gathered afterwards through a raster of vertex indices: that spares
    a full-size int32 index raster and two full passes (docs/BENCHMARKS.md).
    """
    out = np.full((height, width), np.nan, dtype=np.float32)
    cls = np.zeros((height, width), dtype=np.uint8)
    with_colour = colours.shape[0] > 0
    colour = np.zeros((height, width, 3) if with_colour else (0, 0, 3), dtype=np.uint8)
    for t in range(tris.shape[0]):
        a, b, c = tris[t, 0], tris[t, 1], tris[t, 2]
        ua, va = uv[a, 0], uv[a, 1]
        ub, vb = uv[b, 0], uv[b, 1]
        uc, vc = uv[c, 0], uv[c, 1]
        area = (ub - ua) * (vc - va) - (vb - va) * (uc - ua)
        if area == 0.0:
            continue
        c0 = max(int(math.ceil(min(ua, ub, uc))), 0)
        c1 = min(int(math.floor(max(ua, ub, uc))), width - 1)
        r0 = max(int(math.ceil(min(va, vb, vc))), 0)
        r1 = min(int(math.floor(max(va, vb, vc))), height - 1)
        if c0 > c1 or r0 > r1:
            continue
        inv_area = 1.0 / area
        # barycentric weight of a: signed area of (p, b, c) / area, affine in (col, row)
        wa_u = (vb - vc) * inv_area
        wa_v = (uc - ub) * inv_area
        wa_0 = (ub * vc - uc * vb) * inv_area
        wb_u = (vc - va) * inv_area
        wb_v = (ua - uc) * inv_area
        wb_0 = (uc * va - ua * vc) * inv_area
        ia, ib, ic = 1.0 / depth[a], 1.0 / depth[b], 1.0 / depth[c]
        # 1/z = wa ia + wb ib + (1 − wa − wb) ic
        iz_u = wa_u * (ia - ic) + wb_u * (ib - ic)
        iz_v = wa_v * (ia - ic) + wb_v * (ib - ic)
        iz_0 = wa_0 * (ia - ic) + wb_0 * (ib - ic) + ic
        # |p − a|² − |p − b|² = 2 p·(b − a) + |a|² − |b|², likewise for (a, c) and (b, c)
        ab_u, ab_v, ab_0 = 2 * (ub - ua), 2 * (vb - va), ua * ua + va * va - ub * ub - vb * vb
        ac_u, ac_v, ac_0 = 2 * (uc - ua), 2 * (vc - va), ua * ua + va * va - uc * uc - vc * vc
        wc_u, wc_v, wc_0 = -wa_u - wb_u, -wa_v - wb_v, 1.0 - wa_0 - wb_0
        inv_a, inv_b, inv_c = _inverse(wa_u), _inverse(wb_u), _inverse(wc_u)
        for r in range(r0, r1 + 1):
            # the columns where all three weights are >= 0 (pixel centre inside or on an edge)
            lo, hi = float(c0), float(c1)
            lo, hi = _span(wa_u, inv_a, wa_v * r + wa_0, lo, hi)
            lo, hi = _span(wb_u, inv_b, wb_v * r + wb_0, lo, hi)
            lo, hi = _span(wc_u, inv_c, wc_v * r + wc_0, lo, hi)
            if lo > hi:
                continue
            first, last = int(math.ceil(lo)), int(math.floor(hi))
            iz = iz_u * first + iz_v * r + iz_0
            dab = ab_u * first + ab_v * r + ab_0
            dac = ac_u * first + ac_v * r + ac_0
            for col in range(first, last + 1):
                z = 1.0 / iz
                if not (z >= out[r, col]):  # nearer, or the first (NaN)
                    out[r, col] = z
                    # selects, not branches: which vertex is nearest changes unpredictably
                    # from pixel to pixel (a fifth of the time as an if/elif chain)
                    not_a = (dab > 0.0) | (dac > 0.0)  # b or c is nearer than a
                    k = c if dac - dab > 0.0 else b  # of b and c, the nearer (tie: b)
                    k = k if not_a else a
                    cls[r, col] = classes[k]
                    if with_colour:
                        colour[r, col, 0] = colours[k, 0]
                        colour[r, col, 1] = colours[k, 1]
                        colour[r, col, 2] = colours[k, 2]
                iz += iz_u
                dab += ab_u
                dac += ac_u
    return out, cls, colour


def rasterise(
    uv: np.ndarray,
    depth: np.ndarray,
    classes: np.ndarray,
    triangles: np.ndarray,
    shape: tuple[int, int],
    colours: np.ndarray | None = None,
) -> ViewSurface:
    """Depth, class and (with ``colours``) colour rasters of ``triangles`` over the points
    (see module docstring).

    uv (N, 2) float64 px, depth (N,) float64 m, classes (N,) uint8, triangles (T, 3) int
    indices, shape (H, W), colours (N, 3) uint8 RGB or None. Returns a :class:`ViewSurface`.
    """
    uv, depth = _check_points(uv, depth)
    tris = np.ascontiguousarray(triangles, dtype=np.int32).reshape(-1, 3)
    classes = np.ascontiguousarray(classes, dtype=np.uint8)
    if classes.shape != depth.shape:
        raise InputError(f"classes must be {depth.shape}, got {classes.shape}")
    h, w = int(shape[0]), int(shape[1])
    packed = np.zeros((0, 3), np.uint8)  # (0, 3): no colour raster
    if colours is not None:
        packed = np.ascontiguousarray(colours, dtype=np.uint8).reshape(-1, 3)
        if len(packed) != len(depth):
            raise InputError(f"colours must be ({len(depth)}, 3), got {packed.shape}")
    z, cls, colour = _rasterise(uv, depth, tris, h, w, classes, packed)
    if colours is None:
        return ViewSurface(depth=z, classes=cls, valid=~np.isnan(z))
    if colour.shape != (h, w, 3):  # colours for no point at all: nothing was drawn
        colour = np.zeros((h, w, 3), np.uint8)
    return ViewSurface(depth=z, classes=cls, valid=~np.isnan(z), colour=colour)


def view_surface(
    uv: np.ndarray,
    depth: np.ndarray,
    classes: np.ndarray,
    shape: tuple[int, int],
    params: SurfaceParams,
    *,
    cell_px: int = 1,
    colours: np.ndarray | None = None,
    spacing: tuple[np.ndarray, float] | None = None,
) -> ViewSurface:
    """Per-pixel depth and class of a view from its projected points (paper §3.3).

    Parameters
    ----------
    uv : (N, 2) float64, pixels; depth : (N,) float64, metres, camera z; classes : (N,) uint8.
    shape : (H, W) of the image.
    params : triangle filters, see :func:`triangulate`; cell_px as there.
    colours : (N, 3) uint8 RGB of the points, or None.
    spacing : ((N,) float64 metres, focal length px) or None: each point's cloud spacing
        (:mod:`streetcd.detect.spacing`), which widens the filters by
        ``params.spacing_edge_factor`` and ``params.spacing_jump_factor`` (None: fixed filters).

    Returns
    -------
    ViewSurface: depth (H, W) float32 metres (NaN = no surface), classes (H, W) uint8 (0 = no
    surface), valid (H, W) bool, colour (H, W, 3) uint8 or None.
    """
    uv, depth = _check_points(uv, depth)
    if classes.shape != depth.shape:
        raise InputError(f"classes must be {depth.shape}, got {classes.shape}")
    if int(cell_px) < 1:
        raise InputError(f"cell_px must be >= 1, got {cell_px}")
    h, w = int(shape[0]), int(shape[1])
    if spacing is not None and np.shape(spacing[0]) != depth.shape:
        raise InputError(f"spacing must be {depth.shape}, got {np.shape(spacing[0])}")
    tris = _triangulate(uv, depth, (h, w), w, params, int(cell_px), spacing, classes)
    return rasterise(uv, depth, classes, tris, (h, w), colours)


def _zbuffer_params_for(params: ZBufferParams, width: int) -> ZBufferParams:
    """The z-buffer windows for an image ``width`` px wide: as given, or scaled from
    ``REFERENCE_WIDTH_PX`` when ``params.scale_with_resolution`` is set."""
    if not params.scale_with_resolution:
        return params
    return replace(
        params,
        block_window_px=round(scale_px(params.block_window_px, width)),
        weighted_window_px=round(scale_px(params.weighted_window_px, width)),
    )


def surface_for_view(
    xyz_local: np.ndarray,
    cloud_classes: np.ndarray,
    image: np.ndarray,
    intrinsics: Intrinsics,
    pose: Pose,
    params: DetectParams,
    rgb: np.ndarray | None = None,
    *,
    fill: bool = True,
) -> tuple[ViewSurface, ProjectedPoints]:
    """Project a cloud into a view, z-buffer it (eq. 1–3, metric variant, see
    :mod:`streetcd.detect.zbuffer`) and build the view's surface.

    Parameters
    ----------
    xyz_local : (N, 3) float64, metres, local frame of ``pose``; cloud_classes : (N,) uint8.
    image : (H, W, 3) uint8 RGB, must match ``intrinsics`` in size.
    rgb : (N, 3) colours of the cloud (uint16 LAS colours or uint8), or None: with them the
        surface carries the reference colour raster (:mod:`streetcd.detect.appearance`).
    params : uses ``max_range_m``, ``zbuffer`` (its windows scaled to the image width when
        ``zbuffer.scale_with_resolution``) and ``surface``.
    fill : close the near points of ``surface.point_fill_classes`` into their surface
        (:func:`fill_from_points`); the caller turns it off where the roles are inferred.

    Returns
    -------
    (surface, points): the :class:`ViewSurface` and the points the WWZB kept (their ``index``
    refers to rows of ``xyz_local``). Raises :class:`EmptyViewError` if no point falls in the
    view.
    """
    image = np.asarray(image)
    if image.shape != (intrinsics.height, intrinsics.width, 3):
        raise InputError(
            f"image shape {image.shape} does not match the intrinsics "
            f"({intrinsics.height}, {intrinsics.width}, 3)"
        )
    points = project_cloud(xyz_local, cloud_classes, intrinsics, pose, params.max_range_m)
    if len(points) == 0:
        raise EmptyViewError(
            f"no reference point lies within {params.max_range_m} m in front "
            "of the camera and inside the image"
        )
    zparams = _zbuffer_params_for(params.zbuffer, intrinsics.width)
    focal_px = 0.5 * (intrinsics.fx + intrinsics.fy)
    spacing = _point_spacing(xyz_local, cloud_classes, points, params)
    keep = zbuffer_keep(points, image, zparams, focal_px, spacing)
    kept = points.take(keep)
    colours = None if rgb is None else rgb8(np.asarray(rgb)[kept.index])
    kept_spacing = None if spacing is None else spacing[keep]
    surface = view_surface(
        kept.uv,
        kept.depth,
        kept.classes,
        image.shape[:2],
        params.surface,
        cell_px=zparams.block_window_px,
        colours=colours,
        spacing=None if kept_spacing is None else (kept_spacing, focal_px),
    )
    if fill and params.surface.point_fill_classes:
        reach = reach_px(kept.depth, zparams, focal_px, kept_spacing)
        surface = fill_from_points(surface, kept, reach, params.surface, colours)
    return surface, kept


def reach_px(
    depth: np.ndarray, zparams: ZBufferParams, focal_px: float, spacing: np.ndarray | None
) -> np.ndarray:
    """(N,) float64 px: the adaptive part of each point's reach in the weighted z-buffer,
    ``f · s / z`` with ``s = max(point_spacing_m, spacing_factor · spacing)`` (the cloud's
    measured spacing of its class, (N,) metres, or None: ``point_spacing_m`` alone), for
    points at camera depth ``depth`` (N,) metres. The z-buffer's window also has a floor of
    ``weighted_window_px / 2``, left out here: only near points, far above it, use this
    (:mod:`streetcd.detect.zbuffer` applies the same rule inside its kernel)."""
    s = np.full(depth.shape, float(zparams.point_spacing_m))
    if spacing is not None:
        s = np.maximum(s, zparams.spacing_factor * np.asarray(spacing, np.float64))
    return focal_px * s / np.asarray(depth, np.float64)


POINT_FILL_MAX_WIDTH = 0.1
"""The largest disc :func:`fill_from_points` draws, as a share of the image width: a bound on
its cost for points nearly at the camera (a disc keeps only its core when alone)."""


def fill_from_points(
    surface: ViewSurface,
    points: ProjectedPoints,
    reach: np.ndarray,
    params: SurfaceParams,
    colours: np.ndarray | None = None,
) -> ViewSurface:
    """``surface`` with the gaps between the near points of ``params.point_fill_classes``
    filled by those points (our addition, issue 16; :class:`streetcd.config.SurfaceParams`).

    points : the points the surface was built from (z-buffered), with ``reach`` (N,) px each
    (:func:`reach_px`) and ``colours`` (N, 3) uint8 or None. Each point of those roles whose
    disc, ``point_fill_reach`` × its reach px in radius, is at least ``point_fill_min_px``
    stands for that disc; where discs overlap the nearest point's wins. A pixel is filled
    when it lies at least ``point_fill_core`` × its disc's radius inside the discs' union
    (a closing of the points: the gaps between a pole's scan profiles fill, and the union's
    edge, which runs a disc's radius past the outer points, does not), and the surface there
    is a hole or lies more than ``max_depth_jump_m`` behind the point. Filled pixels take
    the point's depth, class and colour. The rasters are updated in place; returned for
    chaining."""
    h, w = surface.depth.shape
    table = np.zeros(256, bool)
    table[np.asarray(params.point_fill_classes, np.int64)] = True
    radius = params.point_fill_reach * np.asarray(reach, np.float64)
    sel = np.flatnonzero(table[points.classes] & (radius >= params.point_fill_min_px))
    if sel.size == 0:
        return surface
    radius = np.minimum(radius[sel], POINT_FILL_MAX_WIDTH * w)
    uv = points.uv[sel]
    # the discs' box, one pixel wider: the union's edge has unfilled pixels on both sides
    c0 = max(0, int(np.floor((uv[:, 0] - radius).min())) - 1)
    c1 = min(w, int(np.ceil((uv[:, 0] + radius).max())) + 2)
    r0 = max(0, int(np.floor((uv[:, 1] - radius).min())) - 1)
    r1 = min(h, int(np.ceil((uv[:, 1] + radius).max())) + 2)
    if c0 >= c1 or r0 >= r1:
        return surface
    near = np.full((r1 - r0, c1 - c0), np.inf, np.float32)
    disc = np.zeros(near.shape, np.float32)
    owner = np.full(near.shape, -1, np.int32)
    _draw_discs(uv - (c0, r0), points.depth[sel], radius, near, disc, owner)
    claimed = owner >= 0
    inside = cv2.distanceTransform(claimed.astype(np.uint8), cv2.DIST_L2, 5)
    box = np.s_[r0:r1, c0:c1]
    z = surface.depth[box]
    fill = claimed & (inside >= params.point_fill_core * disc)
    fill &= ~(z <= near + params.max_depth_jump_m)  # a hole (NaN) or farther behind
    if not fill.any():
        return surface
    idx = sel[owner[fill]]
    z[fill] = points.depth[idx]
    surface.classes[box][fill] = points.classes[idx]
    surface.valid[box][fill] = True
    if surface.colour is not None and colours is not None:
        surface.colour[box][fill] = colours[idx]
    return surface


@numba.njit(cache=True, nogil=True)
def _draw_discs(uv, depth, radius, near, disc, owner):  # pragma: no cover - compiled
    """Each point i a disc of ``radius[i]`` px around ``uv[i]`` (column, row) in the (H, W)
    rasters: where it is the nearest so far, ``near`` takes its depth, ``disc`` its radius
    and ``owner`` its index i."""
    h, w = near.shape
    for i in range(depth.shape[0]):
        cu, cv, r = uv[i, 0], uv[i, 1], radius[i]
        r2 = r * r
        for y in range(max(0, int(cv - r)), min(h - 1, int(cv + r) + 1) + 1):
            dy = y - cv
            for x in range(max(0, int(cu - r)), min(w - 1, int(cu + r) + 1) + 1):
                dx = x - cu
                if dx * dx + dy * dy <= r2 and depth[i] < near[y, x]:
                    near[y, x] = depth[i]
                    disc[y, x] = r
                    owner[y, x] = i


def zbuffer_keep(
    points: ProjectedPoints,
    image: np.ndarray,
    zparams: ZBufferParams,
    focal_px: float,
    spacing: np.ndarray | None,
) -> np.ndarray:
    """Indices of the projected ``points`` the metric z-buffer keeps (eq. 1–3,
    :func:`streetcd.detect.zbuffer.weighted_zbuffer`) in ``image`` (H, W, 3) uint8, each
    point's window reaching ``zparams.spacing_factor`` × its class spacing ``spacing`` (M,)
    metres (:func:`_point_spacing`; None: ``zparams.point_spacing_m`` alone)."""
    return weighted_zbuffer(
        points.uv,
        points.depth,
        image,
        zparams,
        focal_px=focal_px,
        spacing_m=None if spacing is None else zparams.spacing_factor * spacing,
    )


def _point_spacing(
    xyz_local: np.ndarray, cloud_classes: np.ndarray, points: ProjectedPoints, params: DetectParams
) -> np.ndarray | None:
    """(M,) float64 metres: the cloud's measured spacing of each projected point's class
    (:func:`streetcd.detect.spacing.class_spacing`), or None when no filter uses it."""
    sp, zp = params.surface, params.zbuffer
    if sp.spacing_edge_factor <= 0 and sp.spacing_jump_factor <= 0 and zp.spacing_factor <= 0:
        return None
    return class_spacing(xyz_local, cloud_classes)[points.classes]


def rgb8(rgb: np.ndarray) -> np.ndarray:
    """(N, 3) point colours as uint8: LAS stores 16-bit colours (0–65535), some writers put
    8-bit values in them; a cloud whose largest value is below 256 is taken as 8-bit."""
    rgb = np.asarray(rgb)
    if rgb.dtype == np.uint8:
        return rgb
    if rgb.size and int(rgb.max()) < 256:
        return rgb.astype(np.uint8)
    return (
        (rgb >> 8).astype(np.uint8)
        if rgb.dtype.kind == "u"
        else np.clip(rgb / 257, 0, 255).astype(np.uint8)
    )
