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
evidence, as do pixels no neighbour sees. Computed at ``scale`` of the view's resolution, which
helps it tolerate registration error, and never wider than ``max_work_width_px``, which bounds
its cost on large images.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numba
import numpy as np

from streetcd.config import TextureParams
from streetcd.detect.correlate import HoleDepths, Neighbour, camera_rays, warp_neighbour
from streetcd.types import Intrinsics, Pose


def grey(image: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB → (H, W) float32 grey levels in [0, 255]."""
    return cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY).astype(np.float32)


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
    neighbours: Sequence[tuple[np.ndarray, np.ndarray, Intrinsics, Pose, HoleDepths | None]],
    params: TextureParams,
    occlusion_tolerance_m: float,
    registration_px: float = 0.0,
    where: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """``T_p`` of the module docstring for view ``p``, at full resolution.

    image_p : (H, W, 3) uint8 RGB. depth_p : (H, W) float32 metres, the view's old surface
    (NaN = none). neighbours : (image (h, w, 3) uint8 RGB, depth (h, w) float32, intrinsics,
    pose, holes) per neighbour, poses in the same local frame as ``pose_p``.
    registration_px : the registration error to tolerate, in full-resolution pixels: each
    neighbour's NCC is the best over the warped neighbour shifted by up to that much (at the
    cue's scale), as eq. 5's colour envelope tolerates it for single pixels. where : (H, W)
    bool, the pixels the cue is wanted at (None: all); only the box around them, grown by
    the window, is computed, and the cue is 0 outside it.
    Returns ``change`` (H, W) float32 in [0, 1] and ``support`` (H, W) uint8 (neighbours with
    textured evidence per pixel).
    """
    h, w = depth_p.shape
    s = min(float(params.scale), params.max_work_width_px / w)
    small = (max(1, round(w * s)), max(1, round(h * s)))
    intr_s = intrinsics_p.scaled(small[0] / w)
    depth_s = cv2.resize(depth_p, small, interpolation=cv2.INTER_NEAREST)
    radius = round(registration_px * s)
    box = _box(where, small, params.window_px + radius)
    change_s = np.zeros(depth_s.shape, np.float32)
    support_s = np.zeros(depth_s.shape, np.uint8)
    if box is not None:
        rows, cols = box
        grey_p = cv2.resize(grey(image_p), small, interpolation=cv2.INTER_AREA)[rows, cols]
        rays = camera_rays(intr_s)[rows, cols]
        depth_b = np.ascontiguousarray(depth_s[rows, cols])
        change = np.full(depth_b.shape, np.inf, np.float32)
        support = np.zeros(depth_b.shape, np.uint8)
        tiles = _tiles_near(where, small, box, reach=params.window_px // 2 + radius)
        for nb_image, nb_depth, nb_intr, nb_pose, holes in neighbours:
            nb = Neighbour(grey(nb_image), nb_depth, nb_intr, nb_pose, holes=holes)
            warped, valid = warp_neighbour(nb, depth_b, rays, pose_p, occlusion_tolerance_m)
            ncc, textured = _best_ncc_on(tiles, grey_p, warped, valid, params, radius)
            np.minimum(change, np.clip(1.0 - ncc, 0.0, 1.0), out=change, where=textured)
            support += textured
        change[support == 0] = 0.0
        change_s[rows, cols], support_s[rows, cols] = change, support
    full = cv2.resize(change_s, (w, h), interpolation=cv2.INTER_LINEAR)
    full[~np.isfinite(depth_p)] = 0.0
    if where is not None:
        full[~where] = 0.0
    return full, cv2.resize(support_s, (w, h), interpolation=cv2.INTER_NEAREST)


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


def _best_ncc_on(
    tiles: _Tiles | None,
    a: np.ndarray,
    b: np.ndarray,
    valid: np.ndarray,
    params: TextureParams,
    radius: int,
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_best_ncc` on the pixels of ``tiles`` only (all pixels for None); 0 / False
    elsewhere."""
    if tiles is None:
        return _best_ncc(a, b, valid, params, radius)
    if len(tiles.origins) == 0:
        return np.zeros(a.shape, np.float32), np.zeros(a.shape, bool)
    ncc, textured = _best_ncc(
        tiles.gather(a, 0.0), tiles.gather(b, 0.0), tiles.gather(valid, False), params, radius
    )
    return tiles.scatter(ncc, 0.0), tiles.scatter(textured, False)


def _best_ncc(
    a: np.ndarray, b: np.ndarray, valid: np.ndarray, params: TextureParams, radius: int
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`local_ncc` of ``a`` and ``b`` shifted by every whole-pixel offset up to
    ``radius`` (a square), the best at each pixel; textured where any shift is.

    Per shift, one numba pass writes the six products whose window sums the NCC needs
    (1, a, a², b, b², ab over the pixels valid in both), one six-channel box filter sums
    them, and a second pass keeps the best NCC: the same numbers as :func:`local_ncc`
    shift by shift (up to float32 rounding), without its dozen full-size temporaries."""
    a = np.ascontiguousarray(a, np.float32)
    b = np.ascontiguousarray(b, np.float32)
    valid = np.ascontiguousarray(valid, np.bool_)
    best = np.full(a.shape, -1.0, np.float32)
    any_textured = np.zeros(a.shape, np.bool_)
    products = np.empty((6, *a.shape), np.float32)
    sums = np.empty_like(products)
    k = int(params.window_px)
    enough = np.float32(0.5 * k * k)
    floor = np.float32(params.min_std * params.min_std)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            _products(a, b, valid, dy, dx, products)
            for c in range(6):  # six planes: one plane at a time is twice as fast in OpenCV
                cv2.boxFilter(
                    products[c],
                    cv2.CV_32F,
                    (k, k),
                    sums[c],
                    normalize=False,
                    borderType=cv2.BORDER_CONSTANT,
                )
            _keep_best(sums, valid, dy, dx, enough, floor, best, any_textured)
    best[~any_textured] = 0.0
    return best, any_textured


@numba.njit(cache=True, nogil=True)
def _products(a, b, valid, dy, dx, out):  # pragma: no cover - numba
    """out[y, x] = (1, a, a², b', b'², a·b') with b' = b[y − dy, x − dx], where both pixels are
    valid, else zeros. a, b (H, W) float32, valid (H, W) bool, out (6, H, W) float32."""
    h, w = a.shape
    for y in range(h):
        for x in range(w):
            ys, xs = y - dy, x - dx
            if valid[y, x] and 0 <= ys < h and 0 <= xs < w and valid[ys, xs]:
                av, bv = a[y, x], b[ys, xs]
                out[0, y, x] = 1.0
                out[1, y, x] = av
                out[2, y, x] = av * av
                out[3, y, x] = bv
                out[4, y, x] = bv * bv
                out[5, y, x] = av * bv
            else:
                for c in range(6):
                    out[c, y, x] = 0.0


@numba.njit(cache=True, nogil=True)
def _keep_best(sums, valid, dy, dx, enough, floor, best, any_textured):  # pragma: no cover
    """The NCC of :func:`local_ncc` from the window sums ``sums`` (6, H, W) of
    :func:`_products`; ``best`` (H, W) float32 keeps the largest where textured."""
    h, w = best.shape
    for y in range(h):
        for x in range(w):
            ys, xs = y - dy, x - dx
            if not (valid[y, x] and 0 <= ys < h and 0 <= xs < w and valid[ys, xs]):
                continue
            n = sums[0, y, x]
            if n < enough:
                continue
            ma, mb = sums[1, y, x] / n, sums[3, y, x] / n
            var_a = max(sums[2, y, x] / n - ma * ma, 0.0)
            var_b = max(sums[4, y, x] / n - mb * mb, 0.0)
            if var_a < floor or var_b < floor:
                continue
            ncc = (sums[5, y, x] / n - ma * mb) / np.sqrt(var_a * var_b)
            ncc = min(max(ncc, -1.0), 1.0)
            any_textured[y, x] = True
            if ncc > best[y, x]:
                best[y, x] = ncc
