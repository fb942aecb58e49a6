"""Neighbour re-projection and raw change (paper §3.3, eq. 4–5).

Every neighbouring image ``I_q`` is re-projected onto the reference view ``p`` through the
reference cloud's surface as ``p`` sees it, ``I_qp``, and the raw change is the per-pixel
minimum colour difference over the neighbours (eq. 5).

**Re-projection.** The paper rectifies each pair, interpolates disparity on a triangulation in
``q`` and samples ``q`` along the epipolar line (eq. 4). We do the equivalent directly: every
pixel of ``p`` with a surface depth is back-projected through ``p``'s depth raster to 3D,
projected into ``q``, and ``q``'s image is sampled there bilinearly (``cv2.remap`` in
:func:`warp_neighbour`, which shows ``I_qp`` itself; one fused numba pass per neighbour in
:func:`raw_change`). Both give ``I_qp(x) = I_q(π_q(X_p(x)))`` with ``X_p(x)`` the old
surface point behind pixel ``x``; ours needs no rectification, handles lens distortion and
keeps ``p``'s own triangulation.

**Occlusion.** A surface point of ``p`` that ``q`` does not see (``q``'s own depth raster, from
the same cloud, is closer there by more than the tolerance) gives no evidence from ``q``.
Where ``q`` has no surface at all, nothing is known to hide the point and it is kept.

**Histogram stretching** (Zhang & Main 1990): each image's channels are stretched linearly
between two percentiles to [0, 255], so exposure and white-balance differences between views
(per-channel gains and offsets) cancel before differencing. It is global: a new object that
fills more than the top or bottom percentile of a channel shifts that view's stretch.

**Raw change** ``C_p = min_q min(1, ‖I_p − I_qp‖₂ / 255)`` in [0, 1]: the RGB distance with
channels scaled to [0, 1], clipped at 1 (reached by a full-range difference in one channel).
The paper normalises ``C_p`` to [0, 1] without saying how; a fixed scale keeps a view
without change at a small ``C_p`` (dividing by the image maximum would blow its noise up to
1). With a = 45, b = 11 the S-curve's midpoint C = 0.24 is a difference of about 36 levels
in each channel. Pixels without a surface or without any neighbour that sees them get 0:
no evidence of change. Raw change on the low-weight classes (trees, roads: cars and
foliage) is multiplied by ``low_class_weight``.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numba
import numpy as np

from streetcd.config import CorrelateParams, scale_px
from streetcd.detect.roles import in_roles
from streetcd.errors import InputError
from streetcd.geometry.camera import distort, pixel_rays
from streetcd.types import Intrinsics, Pose

_DEFAULTS = CorrelateParams()  # frozen: one shared default instance

_COLOR_RANGE = 255.0  # 8-bit channel range: C = min(1, ‖ΔRGB‖ / 255)
_RAY_GRID_STEP_PX = 8  # distorted cameras: exact rays on this grid, bilinear in between
PAIR_SAMPLE_STEP_PX = 8  # pair_lut samples every 8th row and column of p's surface
PAIR_MIN_SAMPLES = 100  # ... and falls back to q's own stretch below this many shared pixels
# CorrelateParams.second_smallest: the second-smallest difference counts where at least this
# many neighbours see a pixel (with two, one that disagrees would decide: the minimum stays)
SECOND_SMALLEST_FROM = 3


@dataclass(frozen=True)
class Neighbour:
    """One neighbouring view ready for re-projection, in the cloud's local frame.

    image : (H_q, W_q, 3) float32, histogram-stretched RGB in [0, 255].
    depth : (H_q, W_q) float32 metres, camera z of ``q``'s surface, NaN = no surface.
    envelope : optional (lo, hi) of :func:`colour_envelope` at :func:`raw_change`'s radius
        (:func:`registration_radius_px`), precomputed by :func:`stretched_envelope`; when
        given, :func:`raw_change` uses it and does not read ``image``.
    lut : optional (1, 256, 3) float32 stretch look-up table (:func:`stretch_lut`). With it,
        ``envelope`` holds the (H_q, W_q, 3) uint8 levels *before* the stretch
        (:func:`envelope_levels`) and :func:`raw_change` looks each sample up as it reads
        it: the same values as the float32 envelope, without building two full-size float
        images per neighbour (their memory and time: docs/BENCHMARKS.md).
    holes : optional :class:`HoleDepths` of ``depth`` (:func:`hole_depths`): where ``depth``
        has no surface, the occlusion test reads the nearby minimum depth there instead.
    offset : (dy, dx) the neighbour's registration shift against the view, in pixels of the
        view's rasters that :func:`raw_change` is given (:mod:`streetcd.detect.align`): the
        view's pixel (y, x) is compared with what the neighbour sees of the old surface at
        (y − dy, x − dx), rounded to whole pixels; (0, 0): the poses as given.
    """

    image: np.ndarray
    depth: np.ndarray
    intrinsics: Intrinsics
    pose: Pose
    envelope: tuple[np.ndarray, np.ndarray] | None = None
    lut: np.ndarray | None = None
    holes: HoleDepths | None = None
    offset: tuple[float, float] = (0.0, 0.0)


def stretch_histogram(
    image: np.ndarray, percentiles: tuple[float, float] = (1.0, 99.0), sample_step: int = 4
) -> np.ndarray:
    """Stretch each channel linearly so its ``percentiles`` map to 0 and 255 (clipped).

    image : (H, W, 3) uint8 RGB. Returns (H, W, 3) float32 in [0, 255]. Percentiles are
    taken on every ``sample_step``-th row and column (plenty for a histogram). A flat
    channel (both percentiles equal) is passed through unchanged.
    """
    # one 256-entry look-up per channel
    return cv2.LUT(np.ascontiguousarray(image), stretch_lut(image, percentiles, sample_step))


def stretch_lut(
    image: np.ndarray, percentiles: tuple[float, float] = (1.0, 99.0), sample_step: int = 4
) -> np.ndarray:
    """The (1, 256, C) float32 look-up table :func:`stretch_histogram` applies to ``image``
    (H, W, C) uint8; non-decreasing in the level for every channel."""
    lo_pct, hi_pct = percentiles
    n_channels = image.shape[2]
    sample = image[::sample_step, ::sample_step].reshape(-1, n_channels)
    levels = np.arange(256, dtype=np.float32)
    lut = np.empty((1, 256, n_channels), dtype=np.float32)
    for c in range(n_channels):
        lo, hi = np.percentile(sample[:, c], [lo_pct, hi_pct])
        lut[0, :, c] = (
            np.clip((levels - np.float32(lo)) * np.float32(255.0 / (hi - lo)), 0, 255)
            if hi > lo
            else levels
        )
    return lut


def stretched_envelope(
    image: np.ndarray, radius_px: int, percentiles: tuple[float, float] = (1.0, 99.0)
) -> tuple[np.ndarray, np.ndarray]:
    """``colour_envelope(stretch_histogram(image, percentiles), radius_px)``, bit for bit,
    from the (H, W, 3) uint8 image: the stretch is a non-decreasing map per channel, so it
    commutes with the per-channel minimum and maximum; erode and dilate run on uint8 and
    the look-up follows (faster, docs/BENCHMARKS.md, and no float image besides lo and
    hi)."""
    image = np.ascontiguousarray(image)
    lut = stretch_lut(image, percentiles)
    if radius_px <= 0:
        stretched = cv2.LUT(image, lut)
        return stretched, stretched
    kernel = np.ones((2 * radius_px + 1, 2 * radius_px + 1), np.uint8)
    return (
        cv2.LUT(cv2.erode(image, kernel, borderType=cv2.BORDER_REPLICATE), lut),
        cv2.LUT(cv2.dilate(image, kernel, borderType=cv2.BORDER_REPLICATE), lut),
    )


def envelope_levels(
    image: np.ndarray, radius_px: int, percentiles: tuple[float, float] = (1.0, 99.0)
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`stretched_envelope` before its look-up: ``(lo, hi, lut)`` with lo, hi the
    (H, W, 3) uint8 per-channel minimum and maximum of ``image`` (H, W, 3) uint8 over a
    (2r+1)² window (``image`` itself twice for r = 0) and ``lut`` the (1, 256, 3) float32
    :func:`stretch_lut`, so that ``cv2.LUT(lo, lut), cv2.LUT(hi, lut)`` is
    :func:`stretched_envelope`. For :class:`Neighbour` ``(envelope=(lo, hi), lut=lut)``."""
    image = np.ascontiguousarray(image)
    lut = stretch_lut(image, percentiles)
    if radius_px <= 0:
        return image, image, lut
    kernel = np.ones((2 * radius_px + 1, 2 * radius_px + 1), np.uint8)
    return (
        cv2.erode(image, kernel, borderType=cv2.BORDER_REPLICATE),
        cv2.dilate(image, kernel, borderType=cv2.BORDER_REPLICATE),
        lut,
    )


def pair_lut(
    image_p: np.ndarray,
    depth_p: np.ndarray,
    intrinsics_p: Intrinsics,
    pose_p: Pose,
    image_q: np.ndarray,
    depth_q: np.ndarray,
    intrinsics_q: Intrinsics,
    pose_q: Pose,
    percentiles: tuple[float, float] = (1.0, 99.0),
    occlusion_tolerance_m: float = 0.3,
    step: int = PAIR_SAMPLE_STEP_PX,
    lut_p: np.ndarray | None = None,
    lut_q: np.ndarray | None = None,
    holes_q: HoleDepths | None = None,
) -> np.ndarray:
    """(1, 256, 3) float32 look-up table that takes ``q``'s uint8 levels into ``p``'s
    histogram-stretched scale (:func:`stretch_lut` of ``image_p``), fitted on the pixels
    the two views share (not in the paper).

    The paper stretches each view on its own; that assumes the views show much the same
    mix of colours. Where one view is mostly a bright façade and its neighbour is not, the
    two stretches differ and the whole façade becomes raw change. Here ``p``'s surface is
    sampled every ``step`` px and projected into ``q`` (pixels inside ``q`` and not hidden
    by ``q``'s own surface, as eq. 5 uses them), and per channel ``q``'s levels are mapped
    onto ``p``'s by a gain and an offset fitted robustly to the paired samples
    (:func:`robust_line`; changed pixels and registration error are outliers to it), then
    through ``p``'s stretch. ``q``'s own :func:`stretch_lut` (``lut_q`` when given) when
    fewer than ``PAIR_MIN_SAMPLES`` pixels are shared.

    image_* : (H, W, 3) uint8 RGB; depth_* : (H, W) float32 metres, NaN = no surface;
    poses in the same local frame. lut_p, lut_q : ``stretch_lut`` of ``image_p`` and
    ``image_q`` with ``percentiles``, when the caller has them. holes_q : what hides the
    points behind ``q``'s surface holes (:func:`hole_depths`), as in :func:`raw_change`.
    """
    if lut_p is None:
        lut_p = stretch_lut(image_p, percentiles)
    d = np.ascontiguousarray(depth_p[::step, ::step])
    rays = np.ascontiguousarray(_rays_of(intrinsics_p)[::step, ::step])
    map_u, map_v, z_q = reproject(d, rays, pose_p, intrinsics_q, pose_q)
    h_q, w_q = depth_q.shape
    with np.errstate(invalid="ignore"):
        ok = (map_u > -0.5) & (map_u < w_q - 0.5) & (map_v > -0.5) & (map_v < h_q - 0.5)
    u = np.where(ok, np.rint(np.nan_to_num(map_u)), 0).astype(np.int64)
    v = np.where(ok, np.rint(np.nan_to_num(map_v)), 0).astype(np.int64)
    with np.errstate(invalid="ignore"):
        ok &= ~(_seen_depths(depth_q, holes_q, v, u) < z_q - np.float32(occlusion_tolerance_m))
    if ok.sum() < PAIR_MIN_SAMPLES:
        return stretch_lut(image_q, percentiles) if lut_q is None else lut_q
    ps = image_p[::step, ::step][ok].astype(np.float64)
    qs = image_q[v[ok], u[ok]].astype(np.float64)
    levels = np.arange(256, dtype=np.float64)
    lut = np.empty((1, 256, 3), np.float32)
    for c in range(3):
        gain, offset = robust_line(qs[:, c], ps[:, c])
        lut[0, :, c] = np.interp(levels * gain + offset, levels, lut_p[0, :, c])
    return lut


def robust_line(
    x: np.ndarray, y: np.ndarray, iterations: int = 10, tukey_c: float = 4.685
) -> tuple[float, float]:
    """Gain and offset of ``y ≈ gain · x + offset`` over paired samples (N,) float64, robust
    to the pairs that disagree (changes, registration error at edges, shadows).

    Tukey-biweight IRLS (scale: 1.4826 · MAD of the residuals of the start and of the first
    fit; iterations until the fit stops moving), started from the gain-only
    fit ``median(y / x)``: a camera's exposure and white balance scale its levels (a gamma
    curve keeps a gain a gain), so that start is close. Pairs, not the two marginal
    distributions, are fitted: matching quantiles of two channels that hold a few colour
    modes (a red wall and a beige one) puts a quartile in the gap between modes, and one
    such fit on a seed-5 street took a neighbour's green gain to 0.42 where the pairs said
    1.11 (docs/TUNING.md, fifth round). The gain is kept within [1/4, 4].
    """
    lit = (x > 8.0) & (y > 8.0)  # ratios of near-black levels are noise
    start = float(np.median(y[lit] / x[lit])) if lit.sum() >= 10 else 1.0
    gain, offset = start, 0.0
    scale = 0.0
    for i in range(iterations):
        residual = y - (gain * x + offset)
        if i < 2:  # the scale from the start and from the first fit, then kept
            scale = 1.4826 * float(np.median(np.abs(residual - np.median(residual))))
        if not scale > 0.5:  # the pairs agree to half a level: nothing left to weigh
            break
        t = residual / (tukey_c * scale)
        w = np.maximum(1.0 - t * t, 0.0) ** 2  # Tukey's biweight
        # weighted least squares for (gain, offset), closed form: no BLAS or LAPACK, whose
        # threads cost more than the fit itself on a busy 2-core worker
        wx = w * x
        sw, sx, sy = w.sum(), wx.sum(), (w * y).sum()
        sxx, sxy = (wx * x).sum(), (wx * y).sum()
        det = sw * sxx - sx * sx
        if np.count_nonzero(w) < 10 or not det > 1e-9 * sw * sw:
            break  # too few pairs, or one level only: no slope to fit
        new_gain = (sw * sxy - sx * sy) / det
        new_offset = (sy - new_gain * sx) / sw
        done = abs(new_gain - gain) < 1e-6 and abs(new_offset - offset) < 1e-4
        gain, offset = float(new_gain), float(new_offset)
        if done:
            break
    if not (np.isfinite(gain) and 0.25 <= gain <= 4.0):
        gain, offset = float(np.clip(start, 0.25, 4.0)), 0.0
    return float(gain), float(offset)


@dataclass(frozen=True)
class HoleDepths:
    """What hides the points behind a view's surface holes (:func:`hole_depths`).

    minima : (ceil(H / block), ceil(W / block)) float32 metres, +inf where nothing near.
    block : block size in pixels of the (H, W) depth raster they belong to.
    """

    minima: np.ndarray
    block: int


# A neighbour as the window cues take it (texture, nearer depth): its image (h, w, 3) uint8
# RGB, its old surface's depth (h, w) float32 metres, intrinsics, pose in the view's local
# frame, and its surface holes (:func:`hole_depths`).
NeighbourView = tuple[np.ndarray, np.ndarray, Intrinsics, Pose, HoleDepths | None]

_NO_HOLES = HoleDepths(np.full((1, 1), np.inf, np.float32), 1 << 30)  # every lookup: +inf


def hole_depths(depth: np.ndarray, radius_px: int) -> HoleDepths | None:
    """For each hole of ``depth`` (H, W) float32 metres (NaN = no surface), the smallest
    depth within about ``radius_px`` of it, for the occlusion test of eq. 5 only (not in the
    paper); None for ``radius_px`` 0.

    The surface drops triangles with long edges (:mod:`streetcd.detect.surface`), so an object close
    to ``q``'s camera, a pole a few metres away, is mostly holes between its sparse points,
    and a hole hides nothing: the wall behind the pole, which ``q`` cannot see, was compared
    with the pole's colour (the largest false region on one street, a whole façade strip).
    Reading the nearby minimum depth in holes lets the pole's remaining triangles hide what
    is behind their gaps; pixels with a surface keep their own depth, and a hole next to
    something nearer only hides points farther away (less evidence, never false change).

    The minimum is kept per block of ``b = max(1, radius_px // 8)`` px: per-block minima,
    then a square min filter (``cv2.erode``) of ``ceil(radius_px / b)`` blocks on them. So the
    window reaches ``radius_px`` and at most ``2b`` px more. It is cheap (docs/BENCHMARKS.md),
    and nothing full-size is built (:func:`occluder_depth` fills a full raster for inspection).
    """
    if radius_px <= 0:
        return None
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    block = max(1, int(radius_px) // 8)
    reach = -(-int(radius_px) // block)
    minima = cv2.erode(
        _block_minima(depth, block),
        cv2.getStructuringElement(cv2.MORPH_RECT, (2 * reach + 1, 2 * reach + 1)),
        borderType=cv2.BORDER_REPLICATE,
    )
    return HoleDepths(minima, block)


def occluder_depth(depth: np.ndarray, radius_px: int) -> np.ndarray:
    """``depth`` (H, W) float32 with its holes filled as the occlusion test reads them
    (:func:`hole_depths`; NaN where nothing is near), ``depth`` itself for radius 0."""
    return filled_depth(depth, hole_depths(depth, radius_px))


def filled_depth(depth: np.ndarray, holes: HoleDepths | None) -> np.ndarray:
    """``depth`` (H, W) with its holes read from ``holes`` (NaN where nothing hides them);
    ``depth`` itself without ``holes``."""
    if holes is None:
        return depth
    return _fill_holes(np.ascontiguousarray(depth, dtype=np.float32), holes.minima, holes.block)


def _seen_depths(
    depth: np.ndarray, holes: HoleDepths | None, rows: np.ndarray, cols: np.ndarray
) -> np.ndarray:
    """``depth[rows, cols]`` with holes read from ``holes`` (+inf: nothing hides them)."""
    seen = depth[rows, cols]
    if holes is not None:
        gap = ~(seen > 0)
        seen[gap] = holes.minima[rows[gap] // holes.block, cols[gap] // holes.block]
    return seen


@numba.njit(cache=True, nogil=True)
def _block_minima(depth, block):  # pragma: no cover - compiled
    """(ceil(H / block), ceil(W / block)) float32 minimum of each block's surface depths,
    +inf for a block without surface (NaN compares False, so holes never win)."""
    h, w = depth.shape
    n_cols = (w + block - 1) // block
    out = np.full(((h + block - 1) // block, n_cols), np.inf, np.float32)
    whole = w // block  # blocks with all `block` columns: a fixed inner loop, branch-free
    for r in range(h):
        row = out[r // block]
        for b in range(whole):
            m = row[b]
            for c in range(b * block, (b + 1) * block):
                z = depth[r, c]
                m = z if z < m else m
            row[b] = m
        for c in range(whole * block, w):
            z = depth[r, c]
            if z < row[whole]:
                row[whole] = z
    return out


@numba.njit(cache=True, nogil=True)
def _fill_holes(depth, minima, block):  # pragma: no cover - compiled
    """``depth`` with holes (not > 0) taken from their block's ``minima`` (NaN for +inf)."""
    h, w = depth.shape
    out = np.empty_like(depth)
    for r in range(h):
        row = minima[r // block]
        for b in range(row.shape[0]):
            fill = row[b] if row[b] < np.inf else np.float32(np.nan)
            for c in range(b * block, min((b + 1) * block, w)):
                z = depth[r, c]
                out[r, c] = z if z > 0.0 else fill
    return out


def pinhole_axes(intrinsics: Intrinsics) -> tuple[np.ndarray, np.ndarray]:
    """(W,) and (H,) float32: x/z of every column's and y/z of every row's pixel centres of a
    camera without distortion, whose normalised coordinates separate so."""
    w, h = intrinsics.width, intrinsics.height
    x = ((np.arange(w, dtype=np.float32) - intrinsics.cx) / intrinsics.fx).astype(np.float32)
    y = ((np.arange(h, dtype=np.float32) - intrinsics.cy) / intrinsics.fy).astype(np.float32)
    return x, y


def camera_rays(intrinsics: Intrinsics) -> np.ndarray:
    """(H, W, 2) float32 undistorted normalised coordinates (x/z, y/z) of every pixel centre.

    With distortion the iterative undistortion runs only on a coarse grid (every
    ``_RAY_GRID_STEP_PX`` px) and is interpolated bilinearly: distortion is smooth (error
    ≈ 1e-5, a hundredth of a pixel at f = 1000 px), and this is far cheaper
    (docs/BENCHMARKS.md).
    """
    h, w = intrinsics.height, intrinsics.width
    if not intrinsics.has_distortion:
        x, y = pinhole_axes(intrinsics)
        return np.stack(np.broadcast_arrays(x[None, :], y[:, None]), axis=-1)
    s = _RAY_GRID_STEP_PX
    gu = np.arange(0, max(w - 1, 1) + s, s, dtype=np.float64)  # ≥ 2 samples, last ≥ W − 1
    gv = np.arange(0, max(h - 1, 1) + s, s, dtype=np.float64)
    uu, vv = np.meshgrid(gu, gv)
    rays = pixel_rays(np.column_stack([uu.ravel(), vv.ravel()]), intrinsics)
    coarse = rays[:, :2].reshape(len(gv), len(gu), 2).astype(np.float32)
    # separable bilinear interpolation with exact weights (cv2.remap quantises them to 1/32)
    return _lerp(_lerp(coarse, w, s, axis=1), h, s, axis=0)


def _rays_of(intrinsics: Intrinsics) -> np.ndarray:
    """:func:`camera_rays`, read-only, shared by the calls with the same camera (the last
    two kept): a street's views share their camera, and building the (H, W, 2) rays anew
    for every raw change cost time (docs/BENCHMARKS.md; its large allocation is the
    cost)."""
    try:
        return _shared_rays(intrinsics)
    except TypeError:  # unhashable (``dist`` given as a list): not shared
        return camera_rays(intrinsics)


@functools.lru_cache(maxsize=2)
def _shared_rays(intrinsics: Intrinsics) -> np.ndarray:
    rays = camera_rays(intrinsics)
    rays.flags.writeable = False
    return rays


def _lerp(a: np.ndarray, n_out: int, step: int, axis: int) -> np.ndarray:
    """Linear interpolation of samples ``a`` taken every ``step`` px along ``axis`` at the
    pixel positions 0..n_out−1."""
    pos = np.arange(n_out, dtype=np.float64) / step
    i0 = np.minimum(pos.astype(np.int64), a.shape[axis] - 2)
    shape = [1] * a.ndim
    shape[axis] = n_out
    f = (pos - i0).astype(np.float32).reshape(shape)
    a0 = np.take(a, i0, axis=axis)
    return a0 + (np.take(a, i0 + 1, axis=axis) - a0) * f


def reproject(
    depth_p: np.ndarray, rays_p: np.ndarray, pose_p: Pose, intrinsics_q: Intrinsics, pose_q: Pose
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each pixel of ``p``'s surface lands in ``q``.

    depth_p : (H, W) float32 metres, camera z in ``p``, NaN = no surface.
    rays_p : (H, W, 2) float32 from :func:`camera_rays` of ``p``.
    pose_p, pose_q : world→camera poses in the same local frame.

    Returns ``map_u, map_v`` (H, W) float32 pixel coordinates in ``q`` (OpenCV convention)
    and ``z_q`` (H, W) float32 depth in ``q``; NaN where ``p`` has no surface or the point
    is behind ``q``. Computed in float32 with the relative pose ``q ← p`` (local frames keep
    coordinates small, so float32 is millimetre-exact at street ranges).
    """
    R_rel = (pose_q.R @ pose_p.R.T).astype(np.float32)  # X_q = R_rel X_p + t_rel
    t_rel = (pose_q.t - pose_q.R @ pose_p.R.T @ pose_p.t).astype(np.float32)
    if not intrinsics_q.has_distortion:  # one compiled pass, the same float32 operations
        cam = np.array(
            [intrinsics_q.fx, intrinsics_q.fy, intrinsics_q.cx, intrinsics_q.cy], np.float32
        )
        return _reproject_pinhole(
            np.asarray(depth_p, np.float32), np.asarray(rays_p, np.float32), R_rel, t_rel, cam
        )
    x = rays_p[..., 0] * depth_p
    y = rays_p[..., 1] * depth_p
    z = depth_p
    xq = R_rel[0, 0] * x + R_rel[0, 1] * y + R_rel[0, 2] * z + t_rel[0]
    yq = R_rel[1, 0] * x + R_rel[1, 1] * y + R_rel[1, 2] * z + t_rel[1]
    zq = R_rel[2, 0] * x + R_rel[2, 1] * y + R_rel[2, 2] * z + t_rel[2]
    zq[~(zq > 1e-3)] = np.nan
    xn, yn = xq / zq, yq / zq
    if intrinsics_q.has_distortion:
        xn, yn = distort(xn, yn, intrinsics_q.dist)
    map_u = (np.float32(intrinsics_q.fx) * xn + np.float32(intrinsics_q.cx)).astype(np.float32)
    map_v = (np.float32(intrinsics_q.fy) * yn + np.float32(intrinsics_q.cy)).astype(np.float32)
    return map_u, map_v, zq.astype(np.float32)


@numba.njit(cache=True, nogil=True)
def _reproject_pinhole(depth, rays, R, t, cam):  # pragma: no cover - compiled
    """:func:`reproject` into a camera without distortion, pixel by pixel in float32 in the
    order numpy evaluates it there (no temporaries: a third of its time at 0.5 MP)."""
    h, w = depth.shape
    map_u = np.empty((h, w), np.float32)
    map_v = np.empty((h, w), np.float32)
    z_q = np.empty((h, w), np.float32)
    nan = np.float32(np.nan)
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    for r in range(h):
        for c in range(w):
            d = depth[r, c]
            x = rays[r, c, 0] * d
            y = rays[r, c, 1] * d
            xq = R[0, 0] * x + R[0, 1] * y + R[0, 2] * d + t[0]
            yq = R[1, 0] * x + R[1, 1] * y + R[1, 2] * d + t[1]
            zq = R[2, 0] * x + R[2, 1] * y + R[2, 2] * d + t[2]
            if not (zq > np.float32(1e-3)):
                zq = nan
            map_u[r, c] = fx * (xq / zq) + cx
            map_v[r, c] = fy * (yq / zq) + cy
            z_q[r, c] = zq
    return map_u, map_v, z_q


def warp_neighbour(
    neighbour: Neighbour,
    depth_p: np.ndarray,
    rays_p: np.ndarray,
    pose_p: Pose,
    occlusion_tolerance_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """``I_qp`` of eq. 4: ``q``'s image sampled where ``p``'s surface points land in ``q``.

    Returns the warped image (H, W, 3) float32 and ``valid`` (H, W) bool: ``p`` has a
    surface, it projects inside ``q`` in front of the camera, and ``q`` does not see
    something closer than ``z_q − occlusion_tolerance_m`` there (nearest-pixel lookup in
    ``q``'s depth raster; bilinear would blend depths across occlusion edges).
    """
    map_u, map_v, z_q = reproject(depth_p, rays_p, pose_p, neighbour.intrinsics, neighbour.pose)
    h_q, w_q = neighbour.depth.shape
    with np.errstate(invalid="ignore"):
        valid = (map_u >= -0.5) & (map_u < w_q - 0.5) & (map_v >= -0.5) & (map_v < h_q - 0.5)
    map_u[~valid] = -1e4  # finite, far outside: remap leaves the border value there
    map_v[~valid] = -1e4
    seen = cv2.remap(
        filled_depth(neighbour.depth, neighbour.holes),
        map_u,
        map_v,
        cv2.INTER_NEAREST,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=np.nan,
    )
    with np.errstate(invalid="ignore"):
        occluded = seen < z_q - np.float32(occlusion_tolerance_m)
    valid &= ~occluded
    warped = cv2.remap(
        neighbour.image, map_u, map_v, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    return warped, valid


def color_distance(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """min(1, ‖a − b‖₂ / 255) over the last axis: (H, W, 3) float32 RGB in [0, 255] pairs →
    (H, W) float32 in [0, 1]."""
    d = a - b
    dist = np.sqrt(np.einsum("...c,...c->...", d, d)) / np.float32(_COLOR_RANGE)
    return np.minimum(dist, np.float32(1.0))


def registration_radius_px(width: int, params: CorrelateParams = _DEFAULTS) -> int:
    """Radius in pixels of the registration tolerance at an image ``width`` px wide:
    ``registration_tolerance_px`` scaled from ``REFERENCE_WIDTH_PX``, but not below
    ``registration_floor_px`` (0 with no tolerance at all)."""
    if params.registration_tolerance_px <= 0:
        return 0
    scaled = scale_px(params.registration_tolerance_px, width, minimum=0.0)
    return int(round(max(scaled, params.registration_floor_px)))


def colour_envelope(image: np.ndarray, radius_px: int) -> tuple[np.ndarray, np.ndarray]:
    """Per-channel minimum and maximum of ``image`` (H, W, 3) float32 over a
    (2r+1)² window: (lo, hi), both (H, W, 3) float32; the image itself twice for r = 0.

    A pixel of ``p`` whose colour lies inside ``q``'s envelope at the re-projected position
    matches some pixel of ``q`` within ``r`` px per channel, so edges shifted by a
    registration error of up to ``r`` px give no raw change (beyond the paper, which relies
    on the graph cut alone to absorb them; see docs/TUNING.md)."""
    image = np.ascontiguousarray(image, dtype=np.float32)
    if radius_px <= 0:
        return image, image
    kernel = np.ones((2 * radius_px + 1, 2 * radius_px + 1), np.uint8)
    return (
        cv2.erode(image, kernel, borderType=cv2.BORDER_REPLICATE),
        cv2.dilate(image, kernel, borderType=cv2.BORDER_REPLICATE),
    )


def raw_change(
    image_p: np.ndarray,
    depth_p: np.ndarray,
    classes_p: np.ndarray,
    intrinsics_p: Intrinsics,
    pose_p: Pose,
    neighbours: Sequence[Neighbour],
    params: CorrelateParams = _DEFAULTS,
    minimum_out: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Raw change ``C_p`` of eq. 5 for view ``p``.

    image_p : (H, W, 3) float32 stretched RGB in [0, 255] (:func:`stretch_histogram`).
    depth_p : (H, W) float32 metres, camera z, NaN = no surface.
    classes_p : (H, W) uint8 class codes of ``p``'s surface.
    pose_p, neighbours : in the cloud's local frame.

    Returns ``change`` (H, W) float32 in [0, 1] (0 where no neighbour gives evidence) and
    ``support`` (H, W) uint8, the number of neighbours that gave evidence at each pixel.
    ``change`` is eq. 5's minimum of the neighbours' differences, or with
    ``params.second_smallest`` their second-smallest where ``SECOND_SMALLEST_FROM`` or more
    neighbours see the pixel (our addition: one neighbour that matches by chance does not
    decide alone). ``minimum_out`` (H, W) float32, if given with ``params.second_smallest``,
    receives eq. 5's minimum, weighted and zeroed as ``change`` is.

    One fused pass per neighbour (:func:`_correlate_into`, numba) does what
    :func:`warp_neighbour` and :func:`color_distance` do, without the ten full-size
    temporaries (faster than them: docs/BENCHMARKS.md).
    """
    image_p = np.ascontiguousarray(image_p, dtype=np.float32)
    depth_p = np.ascontiguousarray(depth_p, dtype=np.float32)
    rays = _rays_of(intrinsics_p)
    change = np.full(depth_p.shape, np.inf, dtype=np.float32)
    second = params.second_smallest
    # the second-smallest difference so far (a 1 × 1 placeholder when it is not wanted)
    change2 = np.full(depth_p.shape if second else (1, 1), np.inf, dtype=np.float32)
    support = np.zeros(depth_p.shape, dtype=np.uint8)
    for nb in neighbours:
        R_rel = nb.pose.R @ pose_p.R.T  # X_q = R_rel X_p + t_rel (camera frames)
        t_rel = nb.pose.t - R_rel @ pose_p.t
        q = nb.intrinsics
        radius = registration_radius_px(q.width, params)
        lo, hi = nb.envelope if nb.envelope is not None else colour_envelope(nb.image, radius)
        holes = nb.holes if nb.holes is not None else _NO_HOLES
        lut = None
        if nb.lut is not None:
            if nb.envelope is None:
                raise InputError("Neighbour.lut needs the uint8 envelope (envelope_levels)")
            lut = np.ascontiguousarray(np.asarray(nb.lut, dtype=np.float32).reshape(256, -1))
        _correlate_into(
            image_p,
            depth_p,
            rays,
            R_rel,
            t_rel,
            np.array([q.fx, q.fy, q.cx, q.cy, *q.dist], dtype=np.float64),
            q.has_distortion,
            lo,
            hi,
            lut,
            radius > 0,
            np.ascontiguousarray(nb.depth, dtype=np.float32),
            holes.minima,
            holes.block,
            float(params.occlusion_tolerance_m),
            change,
            change2,
            second,
            support,
            int(round(nb.offset[0])),
            int(round(nb.offset[1])),
        )
    if second:
        if minimum_out is not None:
            np.copyto(minimum_out, change)
            minimum_out[support == 0] = 0.0
            weigh_low_classes(minimum_out, classes_p, params)
        np.copyto(change, change2, where=support >= SECOND_SMALLEST_FROM)
    change[support == 0] = 0.0
    weigh_low_classes(change, classes_p, params)
    return change, support


def weigh_low_classes(change: np.ndarray, classes: np.ndarray, params: CorrelateParams) -> None:
    """Multiply ``change`` (H, W) float32, in place, by ``params.low_class_weight`` where the
    class code ``classes`` (H, W) uint8 is one of ``params.low_weight_classes`` (trees, roads
    and ground get "a small weight", paper §3.3)."""
    if params.low_weight_classes and params.low_class_weight != 1.0:
        low = in_roles(classes, params.low_weight_classes)  # a look-up, not np.isin
        np.multiply(change, np.float32(params.low_class_weight), out=change, where=low)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _correlate_into(
    image_p,
    depth_p,
    rays,
    R,
    t,
    cam,
    has_dist,
    image_lo,
    image_hi,
    lut,
    envelope,
    depth_q,
    hole_minima,
    hole_block,
    tol,
    change,
    change2,
    second,
    support,
    oy,
    ox,
):  # pragma: no cover - compiled
    """For every pixel of p with a surface: project its 3D point into q, skip it if outside
    q or occluded there (nearest pixel of q's depth closer by more than ``tol``; in a hole,
    its block's entry of ``hole_minima``, blocks of ``hole_block`` px), else sample
    q's colour envelope (``image_lo``/``image_hi``, :func:`colour_envelope`) bilinearly
    (edge pixels replicated), and lower ``change`` to the colour's distance from it (with
    ``second``, ``change2`` keeps the second-smallest distance; else it is not touched).
    cam = (fx, fy, cx, cy, k1, k2, p1, p2, k3) of q. ``lut`` (256, 3) float32: the
    envelope is uint8 levels, stretched through it as they are read; None: float32."""
    image_q = image_lo
    h, w = depth_p.shape
    hq, wq = depth_q.shape
    fx, fy, cx, cy = cam[0], cam[1], cam[2], cam[3]
    k1, k2, p1, p2, k3 = cam[4], cam[5], cam[6], cam[7], cam[8]
    scale = 1.0 / 255.0  # _COLOR_RANGE
    for r in range(h):
        for c in range(w):
            rs, cs = r - oy, c - ox
            if rs < 0 or rs >= h or cs < 0 or cs >= w:
                continue
            z = depth_p[rs, cs]
            if not (z > 0.0):
                continue
            x = rays[rs, cs, 0] * z
            y = rays[rs, cs, 1] * z
            xq = R[0, 0] * x + R[0, 1] * y + R[0, 2] * z + t[0]
            yq = R[1, 0] * x + R[1, 1] * y + R[1, 2] * z + t[1]
            zq = R[2, 0] * x + R[2, 1] * y + R[2, 2] * z + t[2]
            if zq <= 1e-3:
                continue
            xn = xq / zq
            yn = yq / zq
            if has_dist:
                r2 = xn * xn + yn * yn
                radial = 1.0 + r2 * (k1 + r2 * (k2 + r2 * k3))
                xd = xn * radial + 2.0 * p1 * xn * yn + p2 * (r2 + 2.0 * xn * xn)
                yd = yn * radial + p1 * (r2 + 2.0 * yn * yn) + 2.0 * p2 * xn * yn
                xn, yn = xd, yd
            u = fx * xn + cx
            v = fy * yn + cy
            if not (u >= -0.5 and u < wq - 0.5 and v >= -0.5 and v < hq - 0.5):
                continue
            vi, ui = int(v + 0.5), int(u + 0.5)
            seen = depth_q[vi, ui]
            if not (seen > 0.0):  # a hole: what is near it hides (+inf: nothing)
                seen = hole_minima[vi // hole_block, ui // hole_block]
            if seen < zq - tol:
                continue
            u0 = int(np.floor(u))
            v0 = int(np.floor(v))
            fu = u - u0
            fv = v - v0
            ua, ub = max(u0, 0), min(u0 + 1, wq - 1)
            va, vb = max(v0, 0), min(v0 + 1, hq - 1)
            d2 = 0.0
            for ch in range(3):
                low = _bilinear(image_q, lut, va, vb, ua, ub, fu, fv, ch)
                high = low
                if envelope:  # radius 0: lo is hi, skip the second lookup
                    high = _bilinear(image_hi, lut, va, vb, ua, ub, fu, fv, ch)
                # distance to the envelope [low, high]: |p − q| when the radius is 0
                diff = max(image_p[r, c, ch] - high, low - image_p[r, c, ch], 0.0)
                d2 += diff * diff
            d = np.float32(min(1.0, np.sqrt(d2) * scale))
            if d < change[r, c]:
                if second:
                    change2[r, c] = change[r, c]
                change[r, c] = d
            elif second and d < change2[r, c]:
                change2[r, c] = d
            support[r, c] += 1


@numba.njit(cache=True, inline="always")
def _bilinear(image, lut, va, vb, ua, ub, fu, fv, ch):  # pragma: no cover - compiled
    """Channel ``ch`` of ``image`` (through ``lut``, :func:`_level`) interpolated between
    rows ``va``, ``vb`` and columns ``ua``, ``ub`` with weights ``fu``, ``fv``."""
    top = _level(image, lut, va, ua, ch) * (1.0 - fu) + _level(image, lut, va, ub, ch) * fu
    bottom = _level(image, lut, vb, ua, ch) * (1.0 - fu) + _level(image, lut, vb, ub, ch) * fu
    return top * (1.0 - fv) + bottom * fv


@numba.njit(cache=True, inline="always")
def _level(image, lut, r, c, ch):  # pragma: no cover - compiled
    """``image[r, c, ch]``, stretched through ``lut[level, ch]`` when a LUT is given (numba
    drops the branch a None ``lut`` rules out when it compiles)."""
    if lut is None:
        return image[r, c, ch]
    return lut[image[r, c, ch], ch]
