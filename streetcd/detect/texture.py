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
        for nb_image, nb_depth, nb_intr, nb_pose, holes in neighbours:
            nb = Neighbour(grey(nb_image), nb_depth, nb_intr, nb_pose, holes=holes)
            warped, valid = warp_neighbour(nb, depth_b, rays, pose_p, occlusion_tolerance_m)
            ncc, textured = _best_ncc(grey_p, warped, valid, params, radius)
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


def _best_ncc(
    a: np.ndarray, b: np.ndarray, valid: np.ndarray, params: TextureParams, radius: int
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`local_ncc` of ``a`` and ``b`` shifted by every whole-pixel offset up to
    ``radius`` (a square), the best at each pixel; textured where any shift is."""
    best = np.full(a.shape, -1.0, np.float32)
    any_textured = np.zeros(a.shape, bool)
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            b_s, v_s = _shifted(b, dy, dx, 0.0), _shifted(valid, dy, dx, False)
            ncc, textured = local_ncc(a, b_s, v_s & valid, params.window_px, params.min_std)
            np.maximum(best, np.where(textured, ncc, -1.0), out=best)
            any_textured |= textured
    best[~any_textured] = 0.0
    return best, any_textured


def _shifted(x: np.ndarray, dy: int, dx: int, fill: float | bool) -> np.ndarray:
    """``x`` moved by (dy, dx) px: ``out[r, c] = x[r − dy, c − dx]``, ``fill`` where that is
    outside ``x``."""
    out = np.full_like(x, fill)
    h, w = x.shape[:2]
    out[max(dy, 0) : h + min(dy, 0), max(dx, 0) : w + min(dx, 0)] = x[
        max(-dy, 0) : h + min(-dy, 0), max(-dx, 0) : w + min(-dx, 0)
    ]
    return out
