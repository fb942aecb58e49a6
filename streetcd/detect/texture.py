"""Texture cue (not in the paper): does a neighbour, warped onto the view through the old
surface, show the same texture there? Normalised cross-correlation over a window.

Eq. 5 compares single pixels, with a tolerance for registration error: grass re-projected
through a removed pole matches grass a few pixels away, and a removed object in front of a
homogeneous background (road, pavement, foliage) leaves the pixel colours nearly unchanged.
The texture of a window does not survive a wrong depth: with the old surface in front of the
true one, the neighbour's pixels come from the wrong place, shifted by the parallax
``f · b · (1/z_old − 1/z_true)``, and the window's pattern decorrelates, while gain and offset
(light, exposure) leave the NCC unchanged.

For every neighbour ``q``, with ``I_p`` the view's grey levels and ``I_qp`` the neighbour's
warped through the view's surface (eq. 4, :func:`streetcd.detect.correlate.warp_neighbour`),
over a ``w × w`` window ``N(p)`` of pixels where both are valid::

    ncc_q(p) = cov(I_p, I_qp) / sqrt(var(I_p) · var(I_qp))            over N(p)
    T_q(p)   = clip(1 − ncc_q(p), 0, 1)   where both standard deviations ≥ min_std
    T_p      = min_q T_q(p)                (like eq. 5: changed only if no neighbour agrees)

Windows without texture (a standard deviation below ``min_std`` grey levels) give no
evidence, as do pixels no neighbour sees. Computed at ``scale`` of the view's resolution,
which helps it tolerate registration error, and never wider than ``max_work_width_px``, which
bounds its cost on large images.

Registration error is tolerated in two steps: the warped neighbour is first aligned by the one
whole-pixel shift, up to ``max_global_shift_px``, that best correlates it with the view over
the pixels away from the wanted ones (pose error moves a view's pixels nearly alike: mostly a
rotation), then each window takes its best NCC over shifts of up to
``registration_tolerance_px`` around that (what the alignment leaves: roll, depth parallax).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numba
import numpy as np

from streetcd.config import TextureParams, scale_px
from streetcd.detect.boxes import mask_box
from streetcd.detect.correlate import (
    Neighbour,
    NeighbourView,
    camera_rays,
    warp_neighbour,
)
from streetcd.geometry.camera import to_camera
from streetcd.types import Intrinsics, Pose


def grey(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB → (H, W) float32 grey levels in [0, 255]; an (H, W) image is taken
    as grey levels already (as float32)."""
    return np.asarray(grey_u8(image), np.float32)


def shrunk_grey(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Grey levels (float32, :func:`grey`) of ``image`` (H, W, 3) uint8 RGB or (H, W) grey,
    shrunk to ``size`` (W', H') by area averaging; as they are when already that size."""
    g = grey(image)
    if (g.shape[1], g.shape[0]) == tuple(size):
        return g
    return cv2.resize(g, size, interpolation=cv2.INTER_AREA)


def grey_u8(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB → (H, W) uint8 grey levels, the values :func:`grey` gives, at a
    quarter of their memory (a 12 MP image: 12 MB); an (H, W) image is returned as is."""
    if image.ndim == 2:
        return image
    return cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)


def local_ncc(
    a: np.ndarray, b: np.ndarray, valid: np.ndarray, window_px: int, min_std: float
) -> tuple[np.ndarray, np.ndarray]:
    """Normalised cross-correlation of ``a`` and ``b`` (H, W) float32 over ``window_px``
    square windows of the pixels where ``valid`` (H, W) bool holds.

    Returns ``ncc`` (H, W) float32 in [−1, 1] and ``textured`` (H, W) bool: at least half the
    window is valid and both standard deviations are ≥ ``min_std``; ncc is 0 elsewhere.
    """
    w = valid.astype(np.float32)
    a = np.where(valid, a, 0.0).astype(np.float32)
    b = np.where(valid, b, 0.0).astype(np.float32)
    k = (int(window_px), int(window_px))

    def box(x: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(x, cv2.CV_32F, k, normalize=False, borderType=cv2.BORDER_CONSTANT)

    n = box(w)
    enough = n >= 0.5 * window_px * window_px
    n = np.maximum(n, 1.0)
    ma, mb = box(a) / n, box(b) / n
    var_a = np.maximum(box(a * a) / n - ma * ma, 0.0)
    var_b = np.maximum(box(b * b) / n - mb * mb, 0.0)
    cov = box(a * b) / n - ma * mb
    floor = np.float32(min_std * min_std)
    textured = enough & valid & (var_a >= floor) & (var_b >= floor)
    ncc = np.zeros(a.shape, np.float32)
    np.divide(cov, np.sqrt(var_a * var_b), out=ncc, where=textured)
    return np.clip(ncc, -1.0, 1.0), textured


def texture_change(
    image_p: np.ndarray,
    depth_p: np.ndarray,
    intrinsics_p: Intrinsics,
    pose_p: Pose,
    neighbours: Sequence[NeighbourView],
    params: TextureParams,
    occlusion_tolerance_m: float,
    registration_px: float = 0.0,
    where: np.ndarray | None = None,
    blur_px: float = 0.0,
    prepared: WorkingView | None = None,
    near: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``T_p`` of the module docstring for view ``p``, at full resolution.

    image_p : (H, W, 3) uint8 RGB (or (H, W) grey levels, uint8 or float32, of any size with
    the view's aspect: the image is resized to the cue's working size). depth_p : (H, W)
    float32 metres, the view's old surface (NaN = none). neighbours : (image (h, w, 3) uint8
    RGB or (h, w) grey levels, depth (h, w) float32, intrinsics, pose, holes) per neighbour,
    poses in the same local frame as ``pose_p``.
    registration_px : the registration error to tolerate, in full-resolution pixels: each
    neighbour's NCC is the best over the warped neighbour shifted by up to that much (at the
    cue's scale), as eq. 5's colour envelope tolerates it for single pixels. where : (H, W)
    bool, the pixels the cue is wanted at (None: all); only the box around them, grown by
    the window, is computed, and the cue is 0 outside it. ``params.max_global_shift_px``
    (at ``REFERENCE_WIDTH_PX``): the largest shift of the whole warped neighbour against the
    view that :func:`global_shift` looks for (0: none); the shifts of ``registration_px`` are
    searched around the one found. blur_px : σ (px at the cue's scale) of a Gaussian that
    low-passes the view and each warped neighbour before they are compared (0: none;
    ``TextureParams.blur_px``, which the see-through test leaves out: it low-passes itself).
    prepared : the view and ``neighbours`` at the cue's working size (:func:`working_view`,
    the same ``depth_p``, images and poses), read instead of made again; None: made here.
    near : (H, W) bool, the near layer (our addition; :func:`near_layer`): where each
    neighbour's NCC is also taken at the layer's own shift, up to ``params.near_shift_px``
    (:func:`_near_layer`); None: nowhere.
    Returns ``change`` (H, W) float32 in [0, 1] and ``support`` (H, W) uint8 (neighbours with
    textured evidence per pixel).
    """
    h, w = depth_p.shape
    small = work_size(params, (h, w))
    s = work_scale(params, w)
    intr_s = intrinsics_p.scaled(small[0] / w)
    if prepared is not None:
        depth_s = prepared.depth
    else:
        depth_s = cv2.resize(depth_p, small, interpolation=cv2.INTER_NEAREST)
    radius = round(registration_px * s)
    search = round(scale_px(params.max_global_shift_px, w, minimum=0.0) * s)
    box = _box(where, small, params.window_px + radius + search)
    change_s = np.zeros(depth_s.shape, np.float32)
    support_s = np.zeros(depth_s.shape, np.uint8)
    if box is not None:
        rows, cols = box
        view = prepared.grey if prepared is not None else shrunk_grey(image_p, small)
        grey_p = low_pass(view[rows, cols], blur_px)
        rays = (prepared.rays if prepared is not None else camera_rays(intr_s))[rows, cols]
        depth_b = np.ascontiguousarray(depth_s[rows, cols])
        change = np.full(depth_b.shape, np.inf, np.float32)
        support = np.zeros(depth_b.shape, np.uint8)
        tiles = _tiles_near(where, small, box, reach=params.window_px // 2 + radius)
        background = background_mask(where, small, box, params.window_px) if search > 0 else None
        layer = None  # the near layer at the cue's size, over the box
        if near is not None and search > 0:
            small_near = cv2.resize(near.view(np.uint8), small, interpolation=cv2.INTER_NEAREST)
            layer = small_near[rows, cols] > 0
            layer = layer if layer.any() else None
        near_search = round(scale_px(params.near_shift_px, w, minimum=0.0) * s)
        surface = None  # (points, normals) of the view's surface, for the angle test
        if params.min_foreshortening > 0:
            points = surface_points(depth_b, rays)
            surface = (points, surface_normals(points))
        for i, (nb_image, nb_depth, nb_intr, nb_pose, holes) in enumerate(neighbours):
            if prepared is not None:  # the same values as warping the box here
                warped, valid = prepared.warps[i]
                warped, valid = warped[rows, cols], valid[rows, cols].copy()
            else:
                nb = Neighbour(grey(nb_image), nb_depth, nb_intr, nb_pose, holes=holes)
                warped, valid = warp_neighbour(nb, depth_b, rays, pose_p, occlusion_tolerance_m)
            warped = low_pass(warped, blur_px)
            if surface is not None:
                centre = to_camera(nb_pose.center[None], pose_p)[0]  # the neighbour, in p's frame
                valid &= foreshortening(*surface, centre) >= params.min_foreshortening
            offset = (0, 0)
            if background is not None:
                offset = global_shift(grey_p, warped, valid & background, search)
            ncc, textured = _best_ncc_on(
                _reach_for(tiles, offset), grey_p, warped, valid, params, radius, offset
            )
            if layer is not None:
                ncc, textured = _near_layer(
                    ncc,
                    textured,
                    layer,
                    tiles,
                    grey_p,
                    warped,
                    valid,
                    params,
                    radius,
                    offset,
                    near_search,
                )
            np.minimum(change, np.clip(1.0 - ncc, 0.0, 1.0), out=change, where=textured)
            support += textured
        change[support == 0] = 0.0
        change_s[rows, cols], support_s[rows, cols] = change, support
    full = cv2.resize(change_s, (w, h), interpolation=cv2.INTER_LINEAR)
    full[~np.isfinite(depth_p)] = 0.0
    if where is not None:
        full[~where] = 0.0
    return full, cv2.resize(support_s, (w, h), interpolation=cv2.INTER_NEAREST)


@dataclass(frozen=True)
class WorkingView:
    """A view and its neighbours at the texture cue's working size, made once per view
    (:func:`working_view`) for the registration (:mod:`streetcd.detect.align`) and the cue.

    grey : (h, w) float32 the view's grey levels, shrunk (:func:`shrunk_grey`). depth : (h, w)
    float32 metres, its old surface resized nearest. rays : (h, w, 2) float32
    (:func:`~streetcd.detect.correlate.camera_rays` at that size). warps : per neighbour, its
    image warped through that surface (eq. 4): (h, w) float32 grey levels and (h, w) bool
    valid (:func:`~streetcd.detect.correlate.warp_neighbour`).
    """

    grey: np.ndarray
    depth: np.ndarray
    rays: np.ndarray
    warps: list[tuple[np.ndarray, np.ndarray]]


def working_view(
    image_p: np.ndarray,
    depth_p: np.ndarray,
    intrinsics_p: Intrinsics,
    pose_p: Pose,
    neighbours: Sequence[NeighbourView],
    params: TextureParams,
    occlusion_tolerance_m: float,
) -> WorkingView:
    """:class:`WorkingView` of view ``p`` (image (H, W, 3) RGB or (H, W) grey levels, depth
    (H, W) float32 metres) and its ``neighbours`` (as :func:`texture_change` takes them)."""
    h, w = depth_p.shape
    small = work_size(params, (h, w))
    depth_s = cv2.resize(depth_p, small, interpolation=cv2.INTER_NEAREST)
    rays = camera_rays(intrinsics_p.scaled(small[0] / w))
    warps = []
    for nb_image, nb_depth, nb_intr, nb_pose, holes in neighbours:
        nb = Neighbour(grey(nb_image), nb_depth, nb_intr, nb_pose, holes=holes)
        warps.append(warp_neighbour(nb, depth_s, rays, pose_p, occlusion_tolerance_m))
    return WorkingView(shrunk_grey(image_p, small), depth_s, rays, warps)


def low_pass(grey_levels: np.ndarray, sigma: float) -> np.ndarray:
    """``grey_levels`` (H, W) float32 blurred by a Gaussian of ``sigma`` px (a copy; as is for
    ``sigma`` <= 0)."""
    if sigma <= 0:
        return grey_levels
    return cv2.GaussianBlur(grey_levels, (0, 0), sigma)


def work_scale(params: TextureParams, width: int) -> float:
    """The factor the cue shrinks a view ``width`` px wide by: ``params.scale``, or less so
    that it is never wider than ``params.max_work_width_px``."""
    return min(float(params.scale), params.max_work_width_px / width)


def work_size(params: TextureParams, shape: tuple[int, int]) -> tuple[int, int]:
    """(W, H) the cue runs at for a view of ``shape`` (H, W) (:func:`work_scale`)."""
    h, w = shape
    s = work_scale(params, w)
    return max(1, round(w * s)), max(1, round(h * s))


def surface_points(depth: np.ndarray, rays: np.ndarray) -> np.ndarray:
    """(H, W, 3) float32 camera-frame points (metres) of a surface ``depth`` (H, W) float32
    (NaN = none) along ``rays`` (H, W, 2) normalised coordinates (x/z, y/z)."""
    z = depth.astype(np.float32)
    return np.stack([rays[..., 0] * z, rays[..., 1] * z, z], axis=-1)


def surface_normals(points: np.ndarray, step: int = 2) -> np.ndarray:
    """(H, W, 3) float32 normals (not of unit length) of the surface ``points`` (H, W, 3)
    (:func:`surface_points`): the cross product of its central differences ``step`` pixels
    apart; 0 on the border, NaN where a point is missing."""
    return _normals(np.ascontiguousarray(points, np.float32), int(step))


@numba.njit(cache=True, nogil=True)
def _normals(points, step):  # pragma: no cover - numba
    h, w = points.shape[0], points.shape[1]
    out = np.zeros((h, w, 3), np.float32)
    for i in range(step, h - step):
        for j in range(step, w - step):
            ux = points[i, j + step, 0] - points[i, j - step, 0]
            uy = points[i, j + step, 1] - points[i, j - step, 1]
            uz = points[i, j + step, 2] - points[i, j - step, 2]
            vx = points[i + step, j, 0] - points[i - step, j, 0]
            vy = points[i + step, j, 1] - points[i - step, j, 1]
            vz = points[i + step, j, 2] - points[i - step, j, 2]
            out[i, j, 0] = uy * vz - uz * vy
            out[i, j, 1] = uz * vx - ux * vz
            out[i, j, 2] = ux * vy - uy * vx
    return out


def foreshortening(points: np.ndarray, normals: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """(H, W) float32 in [0, 1]: how alike the view (at the origin) and a camera at
    ``centre`` (3,) metres see the surface ``points`` (H, W, 3) with ``normals`` (H, W, 3)
    (:func:`surface_normals`): ``min(r, 1 / r)`` with ``r = |cos θ_q| / |cos θ_p|``, θ the
    angle between a camera's ray and the normal. 1 where there is no normal (no surface, the
    border), so that only a known bad angle removes evidence."""
    c = np.asarray(centre, np.float64)
    return _foreshortening(
        np.ascontiguousarray(points, np.float32),
        np.ascontiguousarray(normals, np.float32),
        float(c[0]),
        float(c[1]),
        float(c[2]),
    )


@numba.njit(cache=True, nogil=True)
def _foreshortening(points, normals, cx, cy, cz):  # pragma: no cover - numba
    h, w = points.shape[0], points.shape[1]
    out = np.ones((h, w), np.float32)
    for i in range(h):
        for j in range(w):
            x, y, z = points[i, j, 0], points[i, j, 1], points[i, j, 2]
            nx, ny, nz = normals[i, j, 0], normals[i, j, 1], normals[i, j, 2]
            qx, qy, qz = cx - x, cy - y, cz - z
            dp = math.sqrt(x * x + y * y + z * z)
            dq = math.sqrt(qx * qx + qy * qy + qz * qz)
            # the normal's own length cancels in the ratio
            cos_p = abs(nx * x + ny * y + nz * z) / max(dp, 1e-6)
            cos_q = abs(nx * qx + ny * qy + nz * qz) / max(dq, 1e-6)
            hi = max(cos_p, cos_q)
            if hi > 0.0 and math.isfinite(hi) and math.isfinite(cos_p + cos_q):
                out[i, j] = min(cos_p, cos_q) / hi
    return out


def _box(
    where: np.ndarray | None, small: tuple[int, int], margin: int
) -> tuple[slice, slice] | None:
    """(rows, cols) of the box around ``where`` at the cue's size ``small`` (W, H), grown by
    ``margin`` px; the whole image without ``where``; None when ``where`` is empty."""
    if where is None:
        return slice(0, small[1]), slice(0, small[0])
    mask = cv2.resize(where.view(np.uint8), small, interpolation=cv2.INTER_NEAREST)
    x, y, bw, bh = cv2.boundingRect(mask)
    if not (bw and bh):
        return None
    x0, y0 = max(0, x - margin), max(0, y - margin)
    x1, y1 = min(small[0], x + bw + margin), min(small[1], y + bh + margin)
    return slice(y0, y1), slice(x0, x1)


TILE_PX = 32
"""Side of the tiles the cue is computed on (at its working width): only tiles near the wanted
pixels are computed, each with its context, so the cost follows the inventory's share of the
image (1-2 % of the pixels, 8-11 % of the tiles on the synthetic streets) and not the box
around it (most of the image)."""


class _Tiles:
    """The ``TILE_PX`` tiles of a (h, w) box that hold wanted pixels, each padded by ``reach``
    px of context (the window's half side plus the largest shift), so that the NCC at a tile's
    pixels computed on its padded copy alone equals the NCC computed on the whole box."""

    def __init__(self, origins: np.ndarray, shape: tuple[int, int], reach: int) -> None:
        self.origins = origins  # (n, 2) int: (row, col) of each tile's corner in the box
        self.shape = shape
        self.reach = reach

    @property
    def side(self) -> int:
        return TILE_PX + 2 * self.reach

    def _grid(self) -> tuple[int, int]:
        """(rows, columns) of the mosaic: near square (OpenCV's box filter is slower on
        tall, narrow images)."""
        cols = max(1, int(np.ceil(np.sqrt(len(self.origins)))))
        return -(-len(self.origins) // cols), cols

    def gather(self, x: np.ndarray, fill: float | bool) -> np.ndarray:
        """(h, w) → the padded tiles side by side in a mosaic, ``fill`` outside the box."""
        t, r, side = TILE_PX, self.reach, self.side
        h, w = self.shape
        padded = np.full((-(-h // t) * t + 2 * r, -(-w // t) * t + 2 * r), fill, x.dtype)
        padded[r : r + h, r : r + w] = x
        rows, cols = self._grid()
        mosaic = np.full((rows * side, cols * side), fill, x.dtype)
        for k, (y, c) in enumerate(self.origins):
            i, j = divmod(k, cols)
            mosaic[i * side : (i + 1) * side, j * side : (j + 1) * side] = padded[
                y : y + side, c : c + side
            ]
        return mosaic

    def holding(self, mask: np.ndarray) -> _Tiles:
        """These tiles less those whose own pixels hold none of ``mask`` ((h, w) bool over
        the box): each pixel lies in one tile, so the NCC at ``mask`` is the same."""
        t = TILE_PX
        keep = [k for k, (y, c) in enumerate(self.origins) if mask[y : y + t, c : c + t].any()]
        return _Tiles(self.origins[keep], self.shape, self.reach)

    def scatter(self, mosaic: np.ndarray, fill: float | bool) -> np.ndarray:
        """The inverse of :meth:`gather` for the tiles' own pixels: (h, w), ``fill`` elsewhere."""
        t, r, side = TILE_PX, self.reach, self.side
        h, w = self.shape
        out = np.full((-(-h // t) * t, -(-w // t) * t), fill, mosaic.dtype)
        _, cols = self._grid()
        for k, (y, c) in enumerate(self.origins):
            i, j = divmod(k, cols)
            out[y : y + t, c : c + t] = mosaic[
                i * side + r : i * side + r + t, j * side + r : j * side + r + t
            ]
        return out[:h, :w]


def _tiles_near(
    where: np.ndarray | None, small: tuple[int, int], box: tuple[slice, slice], reach: int
) -> _Tiles | None:
    """The tiles of ``box`` (at the cue's size ``small``, (W, H)) within 2 px of a pixel of
    ``where`` (full resolution; the 2 px cover the upsampling back to it), or None for every
    pixel of the box (no ``where``)."""
    if where is None:
        return None
    rows, cols = box
    mask = cv2.resize(where.view(np.uint8), small, interpolation=cv2.INTER_NEAREST)
    mask = cv2.dilate(mask, np.ones((5, 5), np.uint8))[rows, cols]
    h, w = mask.shape
    t = TILE_PX
    padded = np.zeros((-(-h // t) * t, -(-w // t) * t), np.uint8)
    padded[:h, :w] = mask
    wanted = padded.reshape(padded.shape[0] // t, t, padded.shape[1] // t, t).any(axis=(1, 3))
    return _Tiles(np.argwhere(wanted) * t, (h, w), reach)


def background_mask(
    where: np.ndarray | None, small: tuple[int, int], box: tuple[slice, slice], margin: int
) -> np.ndarray:
    """(h, w) bool over ``box`` at the cue's size ``small`` (W, H): the pixels farther than
    ``margin`` px from ``where``, on which :func:`global_shift` aligns a neighbour. The wanted
    pixels are the candidates for change: a removed object's own parallax must not be taken
    for registration error (on a sparse real cloud the dense objects are most of the surface).
    """
    rows, cols = box
    if where is None:
        return np.ones((rows.stop - rows.start, cols.stop - cols.start), bool)
    mask = cv2.resize(where.view(np.uint8), small, interpolation=cv2.INTER_NEAREST)
    mask = cv2.dilate(mask, np.ones((2 * margin + 1, 2 * margin + 1), np.uint8))
    return mask[rows, cols] == 0


def near_layer(
    depth: np.ndarray, see_through: np.ndarray | None, params: TextureParams
) -> np.ndarray | None:
    """(H, W) bool, the near layer of a view (our addition, issue 16): the pixels whose old
    surface is nearer than ``params.near_layer_m`` metres, those of see-through objects
    (``see_through``, bool, or None) left out: through a railing's gaps the wall behind
    shows, and aligning on it would take a hedge in the railing's place for the railing.
    None when the layer is off (``near_layer_m`` 0) or empty. depth : (H, W) float32 metres
    (NaN = none)."""
    if params.near_layer_m <= 0:
        return None
    with np.errstate(invalid="ignore"):
        near = depth < params.near_layer_m
    if see_through is not None:
        near &= ~see_through
    return near if near.any() else None


def _near_layer(
    ncc: np.ndarray,
    textured: np.ndarray,
    near: np.ndarray,
    tiles: _Tiles | None,
    grey_p: np.ndarray,
    warped: np.ndarray,
    valid: np.ndarray,
    params: TextureParams,
    radius: int,
    offset: tuple[int, int],
    search: int,
) -> tuple[np.ndarray, np.ndarray]:
    """``ncc`` and ``textured`` of one neighbour (:func:`_best_ncc_on` at the background's
    ``offset``) with the ``near`` pixels (bool, the box's) taking the better of that and the
    NCC at the near layer's own shift: :func:`global_shift` of the warped neighbour over its
    valid near pixels, up to ``search`` px. A pose's translation error δ moves a point by
    f · δ / z px: a pole or a board 9 m away lands off the shift fitted on the wall 16 m
    behind it, while a removed object's pixels, warped through its old depth, show the
    background displaced by the parallax between the two depths, most often far past
    ``search``. Unchanged where the layer is too small to align on (64 px) or its shift is
    the background's."""
    layer = valid & near
    if np.count_nonzero(layer) < 64:
        return ncc, textured
    shift = global_shift(grey_p, warped, layer, search)
    if shift == offset:
        return ncc, textured
    # only the near pixels take this shift's NCC: the tiles without one are not computed
    held = None if tiles is None else tiles.holding(near)
    ncc_near, textured_near = _best_ncc_on(
        _reach_for(held, shift), grey_p, warped, valid, params, radius, shift
    )
    textured_near &= near
    better = textured_near & (~textured | (ncc_near > ncc))
    return np.where(better, ncc_near, ncc), textured | textured_near


def _reach_for(tiles: _Tiles | None, offset: tuple[int, int]) -> _Tiles | None:
    """``tiles`` with their context grown by the larger side of ``offset`` (dy, dx): the
    shifted neighbour's pixels a window reaches must lie in each padded tile."""
    if tiles is None or offset == (0, 0):
        return tiles
    return _Tiles(tiles.origins, tiles.shape, tiles.reach + max(abs(offset[0]), abs(offset[1])))


GLOBAL_SHIFT_MIN_PX = 32
"""The smallest side of an image level :func:`global_shift` searches on (coarser levels have
too few pixels for a shift to stand out)."""


def global_shift(
    a: np.ndarray, b: np.ndarray, valid: np.ndarray, max_shift: int
) -> tuple[int, int]:
    """The whole-pixel shift (dy, dx), each within ``max_shift``, by which ``b`` best matches
    ``a``: the correlation of their band-passed grey levels over the pixels where both are
    ``valid``, with ``b[y - dy, x - dx]`` against ``a[y, x]`` (as :func:`_best_ncc`).

    a, b : (H, W) float32 grey levels; valid : (H, W) bool. Searched coarse to fine on an
    image pyramid (the full square at the coarsest level, ±1 px at each finer one) down to
    half the input's resolution, so it is exact to ±1 px of the input (the windows' own search
    covers that) and costs a few passes over a quarter of the pixels whatever ``max_shift``.
    (0, 0) when nothing correlates.
    """
    dy, dx, _, _ = shift_search(a, b, valid, max_shift, finest_level=1)
    return max(-max_shift, min(max_shift, dy)), max(-max_shift, min(max_shift, dx))


def shift_search(
    a: np.ndarray, b: np.ndarray, valid: np.ndarray, max_shift: int, finest_level: int
) -> tuple[int, int, float, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """:func:`global_shift`'s search down to pyramid level ``finest_level`` (0: the input's own
    pixels), the shift not clamped to ``max_shift`` (the last ±1 px step may pass it), its
    correlation (−2 when nothing correlates), and that level's band-passed ``a``, ``b`` and
    ``valid`` (at the input's size for level 0)."""
    levels = [(np.asarray(a, np.float32), np.asarray(b, np.float32), np.asarray(valid, bool))]
    while (max_shift >> len(levels)) >= 1 and min(levels[-1][0].shape) >= 2 * GLOBAL_SHIFT_MIN_PX:
        levels.append(_half(*levels[-1]))
    finest = min(finest_level, len(levels) - 1)
    dy = dx = 0
    for depth in range(len(levels) - 1, finest - 1, -1):  # at least one level
        la, lb, lv = levels[depth]
        coarsest = depth == len(levels) - 1
        reach = -(-max_shift >> depth) if coarsest else 1  # ceil(max_shift / 2**depth)
        cy, cx = (0, 0) if coarsest else (2 * dy, 2 * dx)
        passed = (band_pass(la, lv), band_pass(lb, lv), lv)
        dy, dx, score = _best_global(*passed, cy, cx, reach)
    return dy << finest, dx << finest, float(score), passed


def _half(
    a: np.ndarray, b: np.ndarray, valid: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One pyramid level down: each 2 × 2 block's mean over its valid pixels, valid where all
    four are (a block across a hole's edge would carry the edge, alike in both images)."""
    h, w = a.shape
    size = (w // 2, h // 2)
    v = valid[: 2 * size[1], : 2 * size[0]].astype(np.float32)
    n = np.maximum(cv2.resize(v, size, interpolation=cv2.INTER_AREA), np.float32(1e-6))

    def mean(x: np.ndarray) -> np.ndarray:
        x = x[: 2 * size[1], : 2 * size[0]] * v
        return cv2.resize(x, size, interpolation=cv2.INTER_AREA) / n

    return mean(a), mean(b), n > 0.999


def band_pass(x: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``x`` less its 5 × 5 mean over the valid pixels: the texture, not the light (0 where
    not valid)."""
    v = valid.astype(np.float32)
    k = (5, 5)
    n = cv2.boxFilter(v, cv2.CV_32F, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
    s = cv2.boxFilter(x * v, cv2.CV_32F, k, normalize=False, borderType=cv2.BORDER_CONSTANT)
    return np.where(valid, x - s / np.maximum(n, 1.0), 0.0).astype(np.float32)


@numba.njit(cache=True, nogil=True)
def _best_global(a, b, valid, cy, cx, reach):  # pragma: no cover - numba
    """The (dy, dx) within ``reach`` of (cy, cx) with the largest :func:`shift_correlation`;
    a, b (H, W) float32, valid (H, W) bool. Returns (dy, dx, that correlation); (cy, cx, −2)
    when no shift has 64 pixels valid in both."""
    best, by, bx = -2.0, cy, cx
    for dy in range(cy - reach, cy + reach + 1):
        for dx in range(cx - reach, cx + reach + 1):
            c, n = shift_correlation(a, b, valid, dy, dx)
            if n >= 64 and c > best:  # NaN (nothing to correlate) is never greater
                best, by, bx = c, dy, dx
    return by, bx, best


@numba.njit(cache=True, nogil=True)
def shift_correlation(a, b, valid, dy, dx):  # pragma: no cover - numba
    """sum(a·b') / sqrt(sum a² · sum b'²) over the pixels valid in both, b' = b[y − dy, x − dx],
    and how many pixels those are; NaN when either sum is 0. a, b (H, W) float32, valid (H, W)
    bool."""
    h, w = a.shape
    sab = saa = sbb = 0.0
    n = 0
    for y in range(max(0, dy), min(h, h + dy)):
        for x in range(max(0, dx), min(w, w + dx)):
            if valid[y, x] and valid[y - dy, x - dx]:
                av, bv = a[y, x], b[y - dy, x - dx]
                sab += av * bv
                saa += av * av
                sbb += bv * bv
                n += 1
    if saa > 0.0 and sbb > 0.0:
        return sab / np.sqrt(saa * sbb), n
    return np.nan, n


def _best_ncc_on(
    tiles: _Tiles | None,
    a: np.ndarray,
    b: np.ndarray,
    valid: np.ndarray,
    params: TextureParams,
    radius: int,
    offset: tuple[int, int] = (0, 0),
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_best_ncc` on the pixels of ``tiles`` only (all pixels for None); 0 / False
    elsewhere."""
    if tiles is None:
        return _best_ncc(a, b, valid, params, radius, offset)
    if len(tiles.origins) == 0:
        return np.zeros(a.shape, np.float32), np.zeros(a.shape, bool)
    ncc, textured = _best_ncc(
        tiles.gather(a, 0.0),
        tiles.gather(b, 0.0),
        tiles.gather(valid, False),
        params,
        radius,
        offset,
    )
    return tiles.scatter(ncc, 0.0), tiles.scatter(textured, False)


def _best_ncc(
    a: np.ndarray,
    b: np.ndarray,
    valid: np.ndarray,
    params: TextureParams,
    radius: int,
    offset: tuple[int, int] = (0, 0),
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`local_ncc` of ``a`` and ``b`` shifted by every whole-pixel offset up to
    ``radius`` (a square) around ``offset`` (dy, dx), the best at each pixel; textured where
    any shift is.

    Only the box of the ``valid`` pixels is computed: every product outside it is 0 and the
    NCC is wanted only inside it, so the box filters over the box alone, with the image's
    zero border, sum the same values (often a small part: the warped neighbours' valid
    pixels on the cue's classes)."""
    best = np.zeros(np.shape(a), np.float32)
    any_textured = np.zeros(np.shape(a), np.bool_)
    box = mask_box(valid)
    if box is None:
        return best, any_textured
    best[box], any_textured[box] = _best_ncc_in(a[box], b[box], valid[box], params, radius, offset)
    return best, any_textured


def _best_ncc_in(
    a: np.ndarray,
    b: np.ndarray,
    valid: np.ndarray,
    params: TextureParams,
    radius: int,
    offset: tuple[int, int],
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_best_ncc`'s per-shift passes over the whole arrays given: one numba pass per
    shift (:func:`_best_over_shifts`) sums the six products the NCC needs (1, a, a², b, b², ab
    over the pixels valid in both) over each window and keeps the best NCC. The same numbers
    as :func:`local_ncc` shift by shift (up to float32 rounding), without its dozen full-size
    temporaries; and those of the products, OpenCV box filters and NCC passes it replaced, to
    the bit on every case measured (float64 sums added in another order could differ in a
    last float32 rounding), at half their time (docs/BENCHMARKS.md)."""
    a = np.ascontiguousarray(a, np.float32)
    b = np.ascontiguousarray(b, np.float32)
    valid = np.ascontiguousarray(valid, np.bool_)
    best = np.full(a.shape, -1.0, np.float32)
    any_textured = np.zeros(a.shape, np.bool_)
    k = int(params.window_px)
    enough = np.float32(0.5 * k * k)
    floor = np.float32(params.min_std * params.min_std)
    _best_over_shifts(
        a, b, valid, offset[0], offset[1], radius, k, enough, floor, best, any_textured
    )
    best[~any_textured] = 0.0
    return best, any_textured


@numba.njit(cache=True, nogil=True)
def _best_over_shifts(
    a, b, valid, oy, ox, radius, k, enough, floor, best, any_textured
):  # pragma: no cover - numba
    """For every shift (dy, dx) within ``radius`` (a square) of (oy, ox): the NCC of
    :func:`local_ncc` over ``k`` × ``k`` windows between ``a`` and b' = b[y − dy, x − dx],
    over the pixels where both are valid; ``best`` (H, W) float32 keeps the largest where
    textured (at least ``enough`` valid pixels, both variances ≥ ``floor``), ``any_textured``
    (H, W) bool where any shift is. a, b (H, W) float32, valid (H, W) bool.

    The window sums run as a box filter does, with the array's zero border: per row of the
    output, each column's sum over the window's rows is updated by the row entering and the
    row leaving (:func:`_add_row_products`), then swept along the row. Sums are in float64,
    as OpenCV's box filter keeps them, and read as float32, as it returns them."""
    h, w = a.shape
    before = k // 2  # rows (columns) of the window before its pixel, as OpenCV anchors it
    after = k - 1 - before
    columns = np.zeros((6, w), np.float64)
    for dy in range(oy - radius, oy + radius + 1):
        for dx in range(ox - radius, ox + radius + 1):
            columns[:] = 0.0
            for y in range(min(after, h)):
                _add_row_products(a, b, valid, dy, dx, y, 1.0, columns)
            for y in range(h):
                if y + after < h:
                    _add_row_products(a, b, valid, dy, dx, y + after, 1.0, columns)
                if y - before - 1 >= 0:
                    _add_row_products(a, b, valid, dy, dx, y - before - 1, -1.0, columns)
                _keep_best_in_row(
                    columns, valid, y, dy, dx, before, after, enough, floor, best, any_textured
                )


@numba.njit(cache=True, nogil=True, inline="always")
def _add_row_products(a, b, valid, dy, dx, y, sign, columns):  # pragma: no cover - numba
    """Add ``sign`` × (1, a, a², b', b'², a·b') of row ``y`` (b' = b[y − dy, x − dx]) to
    ``columns`` (6, W) float64, where both pixels are valid."""
    h, w = a.shape
    ys = y - dy
    if ys < 0 or ys >= h:
        return
    for x in range(w):
        xs = x - dx
        if valid[y, x] and 0 <= xs < w and valid[ys, xs]:
            av, bv = a[y, x], b[ys, xs]
            columns[0, x] += sign
            columns[1, x] += sign * av
            columns[2, x] += sign * (av * av)
            columns[3, x] += sign * bv
            columns[4, x] += sign * (bv * bv)
            columns[5, x] += sign * (av * bv)


@numba.njit(cache=True, nogil=True, inline="always")
def _keep_best_in_row(
    columns, valid, y, dy, dx, before, after, enough, floor, best, any_textured
):  # pragma: no cover - numba
    """Row ``y`` of :func:`_best_over_shifts`: the column sums ``columns`` (6, W) swept into
    window sums (scalars: six arrays would stay in memory), and each pixel valid in both
    images given the NCC of its window."""
    h, w = best.shape
    ys = y - dy
    s0 = s1 = s2 = s3 = s4 = s5 = 0.0
    for x in range(min(after, w)):
        s0, s1, s2, s3, s4, s5 = _swept(s0, s1, s2, s3, s4, s5, columns, x, 1.0)
    for x in range(w):
        if x + after < w:
            s0, s1, s2, s3, s4, s5 = _swept(s0, s1, s2, s3, s4, s5, columns, x + after, 1.0)
        if x - before - 1 >= 0:
            s0, s1, s2, s3, s4, s5 = _swept(s0, s1, s2, s3, s4, s5, columns, x - before - 1, -1.0)
        xs = x - dx
        if not (valid[y, x] and 0 <= ys < h and 0 <= xs < w and valid[ys, xs]):
            continue
        n = np.float32(s0)
        if n < enough:
            continue
        ma, mb = np.float32(s1) / n, np.float32(s3) / n
        var_a = max(np.float32(s2) / n - ma * ma, 0.0)
        var_b = max(np.float32(s4) / n - mb * mb, 0.0)
        if var_a < floor or var_b < floor:
            continue
        ncc = (np.float32(s5) / n - ma * mb) / np.sqrt(var_a * var_b)
        ncc = min(max(ncc, -1.0), 1.0)
        any_textured[y, x] = True
        if ncc > best[y, x]:
            best[y, x] = ncc


@numba.njit(cache=True, nogil=True, inline="always")
def _swept(s0, s1, s2, s3, s4, s5, columns, x, sign):  # pragma: no cover - numba
    """The six window sums with column ``x`` of ``columns`` (6, W) added (``sign`` 1.0) or
    taken away (−1.0): scalars, not an array of six, which stayed in memory (half again the
    time)."""
    return (
        s0 + sign * columns[0, x],
        s1 + sign * columns[1, x],
        s2 + sign * columns[2, x],
        s3 + sign * columns[3, x],
        s4 + sign * columns[4, x],
        s5 + sign * columns[5, x],
    )
