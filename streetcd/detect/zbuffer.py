"""Image z-buffers that decimate a projected point cloud to the points a view sees (paper §3.2).

Two filters, both pure array kernels on projected points (``uv`` pixels, OpenCV convention;
``depth`` camera-frame z in metres, see :mod:`streetcd.geometry.camera`):

* :func:`block_zbuffer` — the block-window z-buffer (BWZB, eq. 1): the image is cut into
  ``w × w`` cells and each cell keeps its nearest point.
* :func:`weighted_zbuffer` — the weighted-window z-buffer (WWZB, eq. 2–3): BWZB with a small
  ``w``, then every kept point is tested against the other kept points in a ``w1 × w1``
  window centred on it. A neighbour *supports* the centre when it is close in the image and
  the image colours under the two points are alike (eq. 2, ``W > τ``); the centre is erased as
  a back-face point when a supporting neighbour is nearer and the angle of eq. 3 exceeds θ.

Choices the paper leaves open, made here:

* A point belongs to the pixel that contains it, ``(col, row) = floor(uv + 0.5)``; cells are
  ``w × w`` blocks of pixels starting at pixel (0, 0). Points outside the image, with a
  non-finite coordinate or with depth ≤ 0 are never kept. Ties in depth keep the lower index.
* Eq. 2's ``Δc`` is the Euclidean RGB distance of the *image* pixels under the two points (the
  cloud's own colour is not used; it is a decade older), ``Δd`` the image distance in pixels.
* Eq. 3 runs over supporting neighbours nearer than the centre (``z_i < z_c``). The paper
  measures the planimetric offset "on the focal plane" against a depth difference. As
  written, the offset is in **pixels** and the depth in metres,
  ``θ = arctan((z_c − z_i) / ‖x_i − x_c‖_px)``, and any steep supporter erases the centre:
  that is what ``focal_px=None`` runs. The angle then depends on the resolution: a back face
  is erased only where it lies more metres behind a front point than it is pixels away from
  it. On a synthetic street at 2 MP this removes only a small share of the back-face points
  that BWZB(5) leaves (docs/BENCHMARKS.md).

  With ``focal_px`` given (:func:`streetcd.detect.surface.surface_for_view` does this), a second,
  scale-free test is added: the offset in **metres** at the supporter's depth,
  ``‖x_i − x_c‖_px · z_i / f``, gives a true 3D angle. On its own that angle would call a
  road or a façade seen at a grazing angle a back face (its depth grows faster along the
  image than sideways) and erase the ground. So the metric test erases only when the steep
  supporters *surround* the centre: no half-plane through it holds them all (the largest
  angular gap between their directions is ≤ 180°). A point seen through the interspaces of
  a nearer surface is surrounded by it; a ground point has its nearer neighbours on one side
  only. On the same street both tests together remove most of those back-face points
  and keep the ground (``benchmarks/surface_choices.py`` prints the counts); the metric
  angle without the surround rule, tried while choosing, removed nearly all of them and
  nearly all of the visible ground too (docs/BENCHMARKS.md). What stays are points near a
  silhouette or behind surfaces whose points are sparser than w1 / 2: the window then holds
  the nearer points on one side only.
* All centres are tested against the same BWZB set (erasures do not cascade), so the result
  does not depend on the order of the points.
* **Adaptive window** (``ZBufferParams.point_spacing_m`` = s > 0, with ``focal_px``): the paper
  asks w1 to "cover at least one front-face point", but a fixed w1 cannot for near objects:
  a street-light pole 1–2 m from the camera, scanned in profiles up to 0.12 m apart, projects its
  points 40–100 px apart, and the wall behind it stays visible through the interspaces. So
  a neighbour i counts within ``r_i = max(w1 / 2, f · s / z_i)`` px of the centre (its own
  projected spacing), and its Δd in eq. 2 is taken in units of ``r_i / (w1 / 2)`` (close
  relative to its spacing). The tests of eq. 3 are unchanged; the wide reach matters only
  through the metric test, so a wall point is erased only where the near points surround
  it. s = 0 gives the paper's fixed window. On the synthetic streets s = 0.12 m (the
  scanner's profile spacing) cut the false positives by 5–10 points (docs/TUNING.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from streetcd.config import ZBufferParams
from streetcd.detect.memo import ArrayMemo
from streetcd.errors import InputError
from streetcd.geometry.camera import distort, in_image, undistort
from streetcd.types import Intrinsics, Pose


@dataclass(frozen=True)
class ProjectedPoints:
    """The points of a cloud that fall in a view.

    uv : (N, 2) float64, pixels (u column, v row), OpenCV convention, inside the image.
    depth : (N,) float64, metres, camera-frame z (> 0).
    classes : (N,) uint8, class codes (:mod:`streetcd.classes`).
    index : (N,) int64, row of each point in the cloud it was projected from.
    """

    uv: np.ndarray
    depth: np.ndarray
    classes: np.ndarray
    index: np.ndarray

    def __len__(self) -> int:
        return int(self.depth.shape[0])

    def take(self, keep: np.ndarray) -> ProjectedPoints:
        """The points selected by ``keep`` ((M,) int64 indices into these points, or a mask)."""
        return ProjectedPoints(
            self.uv[keep], self.depth[keep], self.classes[keep], self.index[keep]
        )


def project_cloud(
    xyz_local: np.ndarray,
    classes: np.ndarray,
    intrinsics: Intrinsics,
    pose: Pose,
    max_range_m: float,
) -> ProjectedPoints:
    """Project a cloud into a view and keep the points the image can show.

    Parameters
    ----------
    xyz_local : (N, 3) float64, metres, local world frame (the frame of ``pose``).
    classes : (N,) uint8, class code per point.
    intrinsics, pose : the view's camera (:mod:`streetcd.geometry.camera` conventions).
    max_range_m : points farther than this from the camera centre (Euclidean, metres) are
        dropped before projecting.

    Returns
    -------
    ProjectedPoints of the points in front of the camera (depth > 0), within range and with
    their pixel inside the image. With lens distortion, points outside the field of view that
    the polynomial folds back into the image are dropped too.
    """
    xyz_local = np.ascontiguousarray(xyz_local, dtype=np.float64)
    if xyz_local.ndim != 2 or xyz_local.shape[1] != 3:
        raise InputError(f"xyz_local must be (N, 3), got shape {xyz_local.shape}")
    classes = np.asarray(classes)
    if classes.shape != (xyz_local.shape[0],):
        raise InputError(f"classes must be ({xyz_local.shape[0]},), got shape {classes.shape}")
    sel, xn, yn, depth = _in_frustum(
        xyz_local,
        chunk_boxes(xyz_local),
        CHUNK_POINTS,
        pose.R,
        pose.t,
        float(max_range_m) ** 2,
        _normalised_bounds(intrinsics),
    )
    # the pinhole + distortion model of streetcd.geometry.camera.project, on the camera-frame points
    if intrinsics.has_distortion:
        xn, yn = distort(xn, yn, intrinsics.dist)
    uv = np.column_stack([intrinsics.fx * xn + intrinsics.cx, intrinsics.fy * yn + intrinsics.cy])
    keep = in_image(uv, intrinsics)
    sel = sel[keep]
    return ProjectedPoints(uv[keep], depth[keep], classes[sel].astype(np.uint8), sel)


CHUNK_POINTS = 4096  # consecutive points per bounding box (scan order keeps them together)
_BOXES = ArrayMemo()  # a cloud's xyz → its boxes


def chunk_boxes(xyz: np.ndarray) -> np.ndarray:
    """(K, 6) float64 (min x, y, z, max x, y, z) of each run of ``CHUNK_POINTS`` consecutive
    points of ``xyz`` (N, 3) float64, kept while the array lives.

    Most of a street's cloud lies behind or beside any one view, and an MLS cloud comes in
    scan order, so runs of consecutive points are compact: :func:`_in_frustum` skips the
    runs whose box lies wholly outside the frustum (docs/BENCHMARKS.md; the gain is smallest
    on a short street that a view sees much of, as in ``benchmarks/per_view.py``).
    The boxes cost one pass over the points, paid by the first view; clouds are not
    modified in place anywhere, which this cache relies on (:class:`streetcd.detect.memo.ArrayMemo`).
    """
    return _BOXES.get(xyz, lambda a: _chunk_boxes(a, CHUNK_POINTS))


@numba.njit(cache=True, nogil=True)
def _chunk_boxes(xyz, chunk):  # pragma: no cover - compiled
    n = xyz.shape[0]
    k = (n + chunk - 1) // chunk
    boxes = np.empty((k, 6), dtype=np.float64)
    for b in range(k):
        for j in range(3):
            boxes[b, j] = np.inf
            boxes[b, 3 + j] = -np.inf
        for i in range(b * chunk, min((b + 1) * chunk, n)):
            for j in range(3):
                v = xyz[i, j]
                if v < boxes[b, j]:
                    boxes[b, j] = v
                if v > boxes[b, 3 + j]:
                    boxes[b, 3 + j] = v
    return boxes


@numba.njit(cache=True, nogil=True)
def _box_outside(box, R, t, max_range2, bounds):  # pragma: no cover - compiled
    """True when no point of ``box`` (6,) can pass :func:`_in_frustum`'s tests: all eight
    corners behind the camera or beyond one side plane of the frustum (each plane runs
    through the camera centre, so a box wholly on its outer side has every point there), or
    the box's nearest point farther than the range. A margin of 1e-9 keeps rounding on the
    safe side."""
    behind = right = left = below = above = True
    for corner in range(8):
        X = box[3] if corner & 1 else box[0]
        Y = box[4] if corner & 2 else box[1]
        Z = box[5] if corner & 4 else box[2]
        z = R[2, 0] * X + R[2, 1] * Y + R[2, 2] * Z + t[2]
        x = R[0, 0] * X + R[0, 1] * Y + R[0, 2] * Z + t[0]
        y = R[1, 0] * X + R[1, 1] * Y + R[1, 2] * Z + t[1]
        behind &= z < -1e-9
        left &= x < bounds[0] * z - 1e-9
        right &= x > bounds[1] * z + 1e-9
        above &= y < bounds[2] * z - 1e-9
        below &= y > bounds[3] * z + 1e-9
    if behind or left or right or above or below:
        return True
    d2 = 0.0  # squared distance from the camera centre C = −Rᵀt to the box
    for j in range(3):
        c = -(R[0, j] * t[0] + R[1, j] * t[1] + R[2, j] * t[2])
        gap = max(box[j] - c, 0.0, c - box[3 + j])
        d2 += gap * gap
    return d2 > max_range2 * (1.0 + 1e-9) + 1e-9


@numba.njit(cache=True, nogil=True)
def _in_frustum(xyz, boxes, chunk, R, t, max_range2, bounds):  # pragma: no cover - compiled
    """Camera-frame points ``R X + t`` in front, within range and inside ``bounds``.

    bounds = (x_lo, x_hi, y_lo, y_hi) on the normalised coordinates x/z, y/z. The range is
    ‖R X + t‖ = ‖X − C‖ (rotations keep lengths). ``boxes`` (:func:`chunk_boxes`) bound each
    run of ``chunk`` points; runs whose box is outside are skipped without reading their
    points (:func:`_box_outside`: the same points are kept). Returns indices (M,) int64 and
    x/z, y/z, z (M,) float64 each, in point order.
    """
    n = xyz.shape[0]
    idx = np.empty(n, dtype=np.int64)
    xn = np.empty(n, dtype=np.float64)
    yn = np.empty(n, dtype=np.float64)
    zs = np.empty(n, dtype=np.float64)
    m = 0
    for b in range(boxes.shape[0]):
        if _box_outside(boxes[b], R, t, max_range2, bounds):
            continue
        # test each coordinate as soon as it is known, z first (faster than computing
        # x, y, z for every point: docs/BENCHMARKS.md)
        for i in range(b * chunk, min((b + 1) * chunk, n)):
            X, Y, Z = xyz[i, 0], xyz[i, 1], xyz[i, 2]
            z = R[2, 0] * X + R[2, 1] * Y + R[2, 2] * Z + t[2]
            if not (z > 0.0):
                continue
            x = R[0, 0] * X + R[0, 1] * Y + R[0, 2] * Z + t[0]
            if x < bounds[0] * z or x > bounds[1] * z:
                continue
            y = R[1, 0] * X + R[1, 1] * Y + R[1, 2] * Z + t[1]
            if y < bounds[2] * z or y > bounds[3] * z or x * x + y * y + z * z > max_range2:
                continue
            idx[m] = i
            xn[m] = x / z
            yn[m] = y / z
            zs[m] = z
            m += 1
    return idx[:m].copy(), xn[:m].copy(), yn[:m].copy(), zs[:m].copy()


def _normalised_bounds(intrinsics: Intrinsics) -> np.ndarray:
    """(4,) float64 box (x_lo, x_hi, y_lo, y_hi) of normalised coordinates x/z, y/z that holds
    the whole image (1 px margin; 10 % with lens distortion).

    With distortion this also drops points far outside the field of view that the polynomial
    (not monotonic there) would fold back into the image.
    """
    w, h = intrinsics.width, intrinsics.height
    if not intrinsics.has_distortion:
        return np.array(
            [
                (-1.5 - intrinsics.cx) / intrinsics.fx,
                (w + 0.5 - intrinsics.cx) / intrinsics.fx,
                (-1.5 - intrinsics.cy) / intrinsics.fy,
                (h + 0.5 - intrinsics.cy) / intrinsics.fy,
            ]
        )
    s = np.linspace(0.0, 1.0, 17)
    border = np.concatenate(
        [
            np.column_stack([s * w - 0.5, np.full_like(s, -0.5)]),
            np.column_stack([s * w - 0.5, np.full_like(s, h - 0.5)]),
            np.column_stack([np.full_like(s, -0.5), s * h - 0.5]),
            np.column_stack([np.full_like(s, w - 0.5), s * h - 0.5]),
        ]
    )
    bx, by = undistort(
        (border[:, 0] - intrinsics.cx) / intrinsics.fx,
        (border[:, 1] - intrinsics.cy) / intrinsics.fy,
        intrinsics.dist,
    )
    # the fixed-point undistortion must have converged, or the border folds
    rx, ry = distort(bx, by, intrinsics.dist)
    if not np.all(
        np.hypot(
            rx * intrinsics.fx + intrinsics.cx - border[:, 0],
            ry * intrinsics.fy + intrinsics.cy - border[:, 1],
        )
        < 0.5
    ):
        raise InputError(
            f"lens distortion {intrinsics.dist} cannot be inverted at the image "
            "border; check the intrinsics"
        )
    mx, my = 0.1 * (bx.max() - bx.min()), 0.1 * (by.max() - by.min())
    return np.array([bx.min() - mx, bx.max() + mx, by.min() - my, by.max() + my])


# --- block-window z-buffer, eq. 1 --------------------------------------------------------


@numba.njit(cache=True, nogil=True)
def _block_cells(uv, depth, height, width, window):  # pragma: no cover - compiled
    """Nearest point per ``window``-cell: (gh·gw,) int64 point index, −1 for empty cells."""
    gw = (width + window - 1) // window
    gh = (height + window - 1) // window
    best = np.full(gh * gw, -1, dtype=np.int64)
    best_z = np.empty(gh * gw, dtype=np.float64)
    for i in range(depth.shape[0]):
        z = depth[i]
        u = uv[i, 0]
        v = uv[i, 1]
        if not (z > 0.0 and math.isfinite(z) and math.isfinite(u) and math.isfinite(v)):
            continue
        col = int(math.floor(u + 0.5))
        row = int(math.floor(v + 0.5))
        if col < 0 or row < 0 or col >= width or row >= height:
            continue
        cell = (row // window) * gw + col // window
        if best[cell] < 0 or z < best_z[cell]:
            best[cell] = i
            best_z[cell] = z
    return best


def _check_points(uv: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    uv = np.ascontiguousarray(uv, dtype=np.float64)
    depth = np.ascontiguousarray(depth, dtype=np.float64)
    if uv.ndim != 2 or uv.shape[1] != 2 or depth.shape != (uv.shape[0],):
        raise InputError(f"uv must be (N, 2) and depth (N,), got {uv.shape} and {depth.shape}")
    return uv, depth


def _sorted_indices(cells: np.ndarray, n: int) -> np.ndarray:
    mask = np.zeros(n, dtype=bool)
    mask[cells[cells >= 0]] = True
    return np.flatnonzero(mask).astype(np.int64)


def block_zbuffer(
    uv: np.ndarray, depth: np.ndarray, shape: tuple[int, int], window_px: int
) -> np.ndarray:
    """Block-window z-buffer (BWZB), paper eq. 1: the nearest point of each ``w × w`` cell.

    Parameters
    ----------
    uv : (N, 2) float64, pixels (u column, v row), OpenCV convention.
    depth : (N,) float64, metres, camera-frame z.
    shape : (H, W) of the image, pixels.
    window_px : w, the cell size in pixels.

    Returns
    -------
    (M,) int64, ascending indices into ``uv`` of the points kept: per non-empty cell the one
    with the smallest depth ``l_j = m_i, z_i = min(z_t)`` (ties: the lower index). Points
    outside the image, non-finite or with depth ≤ 0 are never kept.
    """
    uv, depth = _check_points(uv, depth)
    if int(window_px) < 1:
        raise InputError(f"window_px must be >= 1, got {window_px}")
    h, w = int(shape[0]), int(shape[1])
    cells = _block_cells(uv, depth, h, w, int(window_px))
    return _sorted_indices(cells, depth.shape[0])


# --- weighted-window z-buffer, eq. 2–3 ---------------------------------------------------


@numba.njit(cache=True, nogil=True)
def _packed_cells(cells, uv, depth, image, gh, gw, half, reach_scale, reach_pt):  # pragma: no cover
    """The occupied block cells, packed in row-major order, with what eq. 2–3 read of each.

    ``reach_pt`` (N,) float64 f·s_i px·m per point, or (0,): each point reaches
    ``max(half, max(reach_scale, reach_pt[i]) / z_i)`` px (``reach_scale <= 0`` and (0,): half).

    Returns ``table`` (M, 7) float64 rows (z, u, v, R, G, B, reach) of the M points in
    ``cells``, ``ids`` (M,) int64 their cell indices and ``start`` (gh, gw + 1) int64: the
    occupied cells of grid row ``y`` at columns ``x0 ≤ x < x1`` are the rows
    ``start[y, x0]:start[y, x1]`` of ``table``.

    Why: :func:`_weighted_erase` scans up to (2·r_i / w)² cells per point, r_i large at
    high resolution (near points reach far), and most cells hold no point. Scanning only
    occupied cells, each read from one packed row instead of through the point index into
    ``uv``, ``depth`` and the image, made the scan markedly faster (docs/BENCHMARKS.md).
    """
    start = np.empty((gh, gw + 1), dtype=np.int64)
    m = 0
    for y in range(gh):
        for x in range(gw):
            start[y, x] = m
            if cells[y * gw + x] >= 0:
                m += 1
        start[y, gw] = m
    table = np.empty((m, 7), dtype=np.float64)
    ids = np.empty(m, dtype=np.int64)
    k = 0
    for cell in range(cells.shape[0]):
        i = cells[cell]
        if i < 0:
            continue
        col = int(math.floor(uv[i, 0] + 0.5))
        row = int(math.floor(uv[i, 1] + 0.5))
        table[k, 0] = depth[i]
        table[k, 1] = uv[i, 0]
        table[k, 2] = uv[i, 1]
        table[k, 3] = float(image[row, col, 0])
        table[k, 4] = float(image[row, col, 1])
        table[k, 5] = float(image[row, col, 2])
        scale = reach_scale if reach_pt.shape[0] == 0 else max(reach_scale, reach_pt[i])
        table[k, 6] = half if scale <= 0.0 else max(half, scale / depth[i])
        ids[k] = cell
        k += 1
    return table, ids, start


_EMPTY, _ONE, _ARC, _ERASED = 0, 1, 2, 3  # a centre's steep supporters so far


@numba.njit(cache=True, nogil=True)
def _weighted_erase(
    cells,
    uv,
    depth,
    image,
    window,
    half,
    gamma,
    delta,
    max_log_w,
    tan_theta,
    focal,
    surround,
    reach_scale,
    reach_pt,
    reach_colour,
):  # pragma: no cover - compiled
    """Erase flags for the BWZB points ``cells`` (see :func:`weighted_zbuffer`).

    cells : (gh·gw,) int64 point index per block cell (−1 empty); returns (gh·gw,) bool,
    True where the cell's point is a back-face point by eq. 2–3 with offsets in pixels, or,
    when ``surround``, by the metric reading (offsets px · z_i / ``focal``) with steep
    supporters that surround the centre (no open half-plane through it holds them all).
    A neighbour i counts within ``r_i = max(half, reach_scale / z_i)`` px of the centre
    (``reach_scale = 0``: the fixed ``half``), and its Δd of eq. 2 is taken in units of
    ``r_i / half``; without ``reach_colour``, eq. 2's colour term counts only within
    ``max(half, reach_scale / z_i)`` px (beyond, only the cloud's own sparser spacing
    ``reach_pt`` reaches). Only occupied cells are visited (:func:`_packed_cells`).

    The pairs are visited from the supporter's side: each point i scans the cells within
    its own reach r_i for the farther centres it supports. From the centres' side every
    centre had to scan as far as the largest reach around it, many more pairs
    (docs/BENCHMARKS.md). Each centre keeps the arc of directions its steep supporters
    cover (:func:`_widen_arc`), so the order of the visits does not matter.
    """
    height, width = image.shape[0], image.shape[1]
    gw = (width + window - 1) // window
    gh = (height + window - 1) // window
    table, ids, start = _packed_cells(cells, uv, depth, image, gh, gw, half, reach_scale, reach_pt)
    m = ids.shape[0]
    state = np.zeros(m, dtype=np.uint8)  # _EMPTY, _ONE, _ARC or _ERASED per centre
    arc = np.empty((m, 4), dtype=np.float64)  # (Δu, Δv) of the arc's two ends
    max_dc2 = (max_log_w * delta) ** 2 * (1.0 + 1e-9)  # Δc/δ ≥ −ln τ fails eq. 2 alone
    for i in range(m):
        u, v, reach = table[i, 1], table[i, 2], table[i, 6]
        # eq. 2's colour term counts within the reach a dense cloud's spacing gives
        # (point_spacing_m), or everywhere with reach_colour
        coloured = np.inf if reach_colour else half
        if not reach_colour and reach_scale > 0.0:
            coloured = max(half, reach_scale / table[i, 0])
        # a centre within `reach` px of u_i has its pixel (floor(u + 0.5)) in these cells
        y0 = max(int(math.floor(v - reach + 0.5)), 0) // window
        y1 = min(int(math.floor(v + reach + 0.5)) // window + 1, gh)
        x0 = max(int(math.floor(u - reach + 0.5)), 0) // window
        x1 = min(int(math.floor(u + reach + 0.5)) // window + 1, gw)
        for ny in range(y0, y1):
            for c in range(start[ny, x0], start[ny, x1]):
                dz = table[c, 0] - table[i, 0]
                du = u - table[c, 1]
                dv = v - table[c, 2]
                # eq. 3 looks only at supporting points nearer than the centre (this skips
                # the centre itself, dz = 0), within their reach. One branch for the three
                # tests: each alone is a coin toss for the branch predictor.
                if (dz <= 0.0) | (abs(du) > reach) | (abs(dv) > reach) | (state[c] == _ERASED):
                    continue
                dr = table[i, 3] - table[c, 3]
                dg = table[i, 4] - table[c, 4]
                db = table[i, 5] - table[c, 5]
                dc2 = dr * dr + dg * dg + db * db
                # most pairs differ in colour by more than eq. 2 allows at any distance:
                # reject them before the square roots (max_dc2's margin changes no decision)
                within = (abs(du) <= coloured) & (abs(dv) <= coloured)
                if dc2 > max_dc2 and within:
                    continue
                dd = math.sqrt(du * du + dv * dv)
                # eq. 2: W = exp(−(Δd/γ + Δc/δ)) > τ  ⇔  Δd/γ + Δc/δ < −ln τ, with Δd in
                # units of the supporter's reach: as close relative to its spacing
                shrink = 1.0 if reach <= half else half / reach
                colour = math.sqrt(dc2) / delta if within else 0.0
                if dd * shrink / gamma + colour >= max_log_w:
                    continue
                # eq. 3 as written, offsets in pixels: arctan(dz / dd) > θ  ⇔  dz > tan θ · dd
                if dz > tan_theta * dd:
                    state[c] = _ERASED
                # the metric reading, offsets in metres at the supporter's depth
                elif surround and dz > tan_theta * dd * table[i, 0] / focal:
                    state[c] = _widen_arc(state[c], arc[c], du, dv)
    erase = np.zeros(cells.shape[0], dtype=np.bool_)
    for c in range(m):
        erase[ids[c]] = state[c] == _ERASED
    return erase


@numba.njit(cache=True, inline="always")
def _widen_arc(state, arc, du, dv):  # pragma: no cover - compiled
    """Add direction (du, dv) ≠ 0 to the smallest arc holding a centre's steep supporters.

    ``arc`` (4,) holds the arc's ends (counter-clockwise from the first to the second),
    valid in states ``_ONE`` (both ends the one direction so far) and ``_ARC`` (span in
    (0°, 180°)). Returns the new state: ``_ERASED`` once no arc under 180° holds them all,
    i.e. the largest gap between their directions is ≤ 180°: the supporters surround the
    centre. The arc of such a set is unique, so the order of additions does not matter.
    Signs of cross products decide, with no angles: (a × b) > 0 when b lies less than
    180° counter-clockwise of a.
    """
    if state == _EMPTY:
        arc[0], arc[1], arc[2], arc[3] = du, dv, du, dv
        return _ONE
    after_first = arc[0] * dv - arc[1] * du  # first × d
    before_second = du * arc[3] - dv * arc[2]  # d × second
    if state == _ONE:
        if after_first == 0.0:  # on the line of the one direction: same way, or opposite
            return _ONE if arc[0] * du + arc[1] * dv > 0.0 else _ERASED
        if after_first > 0.0:
            arc[2], arc[3] = du, dv
        else:
            arc[0], arc[1] = du, dv
        return _ARC
    if after_first >= 0.0 and before_second >= 0.0:  # inside the arc
        return _ARC
    if after_first > 0.0:  # beyond the second end, less than 180° from the first
        arc[2], arc[3] = du, dv
        return _ARC
    if before_second > 0.0:  # before the first end, less than 180° from the second
        arc[0], arc[1] = du, dv
        return _ARC
    return _ERASED


def weighted_zbuffer(
    uv: np.ndarray,
    depth: np.ndarray,
    image: np.ndarray,
    params: ZBufferParams,
    *,
    focal_px: float | None = None,
    spacing_m: np.ndarray | None = None,
) -> np.ndarray:
    """Weighted-window z-buffer (WWZB), paper eq. 1–3.

    Parameters
    ----------
    uv : (N, 2) float64, pixels (u column, v row), OpenCV convention.
    depth : (N,) float64, metres, camera-frame z.
    image : (H, W, 3) uint8 RGB, the view's image (its colours drive eq. 2).
    params : w = ``block_window_px``, w1 = ``weighted_window_px``, γ, δ, τ, θ.
    focal_px : the camera's focal length in pixels. None runs eq. 3 as the paper writes it
        (offsets in pixels, any steep supporter erases); a value adds the metric test
        (offsets in metres, steep supporters must surround the centre), so it erases a
        superset, and turns on the adaptive window when ``params.point_spacing_m > 0``
        (neighbour i reaches ``max(w1 / 2, focal_px · s / z_i)`` px). See the module
        docstring.
    spacing_m : (N,) float64 metres per point, or None: with ``focal_px``, point i's s is
        ``max(params.point_spacing_m, spacing_m[i])`` (the cloud's own spacing where it is
        sparser, :mod:`streetcd.detect.spacing`); None: ``point_spacing_m`` for all.

    Returns
    -------
    (M,) int64, ascending indices into ``uv`` of the points kept: the BWZB points (window w)
    that the supporting neighbours in the ``w1 × w1`` window around them do not mark as a
    back face.
    """
    uv, depth = _check_points(uv, depth)
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise InputError(f"image must be (H, W, 3) uint8 RGB, got {image.shape} {image.dtype}")
    if focal_px is not None and not (math.isfinite(focal_px) and focal_px > 0):
        raise InputError(f"focal_px must be a positive number of pixels, got {focal_px}")
    image = np.ascontiguousarray(image)
    h, w = image.shape[:2]
    window = int(params.block_window_px)
    cells = _block_cells(uv, depth, h, w, window)
    half = int(params.weighted_window_px) // 2
    # the adaptive window needs the focal length to turn metres into pixels
    reach_scale = 0.0 if focal_px is None else float(focal_px) * float(params.point_spacing_m)
    reach_pt = np.empty(0, np.float64)
    if spacing_m is not None and focal_px is not None:
        reach_pt = float(focal_px) * np.ascontiguousarray(spacing_m, dtype=np.float64)
        if reach_pt.shape != depth.shape:
            raise InputError(f"spacing_m must be {depth.shape}, got {reach_pt.shape}")
    erase = _weighted_erase(
        cells,
        uv,
        depth,
        image,
        window,
        half,
        float(params.gamma_px),
        float(params.delta_color),
        -math.log(params.tau),
        math.tan(math.radians(params.max_angle_deg)),
        0.0 if focal_px is None else float(focal_px),
        focal_px is not None,
        reach_scale,
        reach_pt,
        bool(params.reach_colour),
    )
    return _sorted_indices(np.where(erase, -1, cells), depth.shape[0])
