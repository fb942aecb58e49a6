"""Intensity check: does the street inventory the old cloud shows still stand out in the image?

**Not in the paper** (issue 16). The reference-colour check (:mod:`streetcd.detect.appearance`)
finds removed objects in front of plain backgrounds by comparing the image with the cloud's
own colours; many real clouds have none, only LiDAR intensity. Intensity cannot be mapped onto
image colours: it depends on the incidence angle and the range as much as on the material, and
it is measured in the near infrared, so two materials alike to a camera can differ to the
scanner and the other way round. What intensity and image share is *structure*: an object the
scanner saw stand out from what surrounds it is a separate thing, and where it still stands
the camera sees something there too.

So the question asked of every pixel ``p`` of an inventory object (poles, signs, railings,
furniture, as for the colour check), where the old surface is that object:

1. **What would the image show if the object were gone?** The image's colour of the object's
   surroundings, ``B_p``: the image averaged over the pixels around the object, nearest scale
   first (:func:`fill_from`, a push-pull over an image pyramid), leaving out the object's own
   footprint (see-through gaps closed, :func:`streetcd.detect.appearance.footprint`) grown by
   the registration tolerance, so that the object, shifted by a pose error, is not its own
   background. Pixels without a surface (sky) count: the camera sees them all.
2. **Does the image look like that?** ``s_p = clip((d₁ − ‖I_p − B_p‖) / (d₁ − d₀), 0, 1)``:
   1 when the image pixel is within ``d₀`` (RGB, 0–441) of the surroundings' colour, 0
   beyond ``d₁``. A removed board in front of a plain wall leaves the wall's colour where
   the board stood: ``s ≈ 1``; a board still there differs from the wall (or the camera
   could never have told them apart).
3. **Did the scanner see the object stand out?** The gate ``g``: the mean over the object (an
   8-connected piece of inventory with a surface) of the log-intensity contrast
   ``|ln i_p − ln i_bg,p|`` to its surroundings (the same fill over the pixels with a
   surface), divided by ``intensity_contrast`` and capped at 1. An object the scanner
   could not tell from its background either is one the camera may not tell apart either
   (plain-painted, the same material): that it looks like its background then says nothing.

``A_p = g · s_p`` on those pixels, opened (a grey erosion, then a dilation) with a (2r+1)²
square for a registration error of up to ``r`` px, as the colour check is. It sees removed
objects, not replaced ones (a hedge where a railing stood stands out as much as the railing
did); eq. 5 and the texture cue see the rest. :func:`streetcd.detect.chain.detect_view` fuses
``max(C_p, k · A_p)`` like the colour check, and only when the cloud has no colours.
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage

from streetcd.config import AppearanceParams, scale_px
from streetcd.detect.appearance import close_width_px, footprint
from streetcd.detect.roles import in_roles

_DEFAULTS = AppearanceParams()
# Intensity is laid out by the surface rasteriser like 8-bit colours: ln(1 + i) of the
# 16-bit value in 256 steps of LN_PER_CODE (4.4 %), a fixed scale, so that codes from
# different crops of one cloud compare (and a contrast threshold in ln units means the same
# on every cloud).
LN_PER_CODE = float(np.log1p(65535.0) / 255.0)
_ENCODE = np.round(np.log1p(np.arange(65536, dtype=np.float64)) / LN_PER_CODE).astype(np.uint8)
FILL_WEIGHT = 0.25  # a pyramid level answers for a pixel where this share of it is background
WORK_WIDTH_PX = 1280  # the surroundings are taken on blocks that bring an image about this wide


def intensity_codes(intensity: np.ndarray | None) -> np.ndarray | None:
    """(N, 3) uint8 grey "colours" of a cloud's (N,) uint16 intensity for the surface
    rasteriser (:func:`streetcd.detect.surface.surface_for_view` ``rgb``): ``ln(1 + i)`` in
    steps of :data:`LN_PER_CODE`, the same in the three channels. None when there is no
    intensity or it is constant (LAS always has the field; all zero means it was not
    recorded)."""
    if intensity is None or len(intensity) == 0:
        return None
    i = np.asarray(intensity)
    if i.dtype != np.uint16:
        i = np.clip(i, 0, 65535).astype(np.uint16)
    if int(i.max()) == int(i.min()):
        return None
    codes = _ENCODE[i]
    return np.repeat(codes[:, None], 3, axis=1)


def fill_from(
    values: np.ndarray, weight: np.ndarray, levels: int = 12, finest: int = 0
) -> np.ndarray:
    """Each pixel's value as its surroundings give it: the ``weight``-ed mean of ``values``
    over a Gaussian pyramid (OpenCV's pyrDown), taken at the finest level where at least
    :data:`FILL_WEIGHT` of the pixel's neighbourhood has weight, blended from coarse to fine
    (a push-pull fill). values : (H, W, C) float32; weight : (H, W) float32 in [0, 1] (1: a
    pixel to fill from). Returns (H, W, C) float32, or with ``finest`` = k the same at pyramid
    level k (each side halved k times, rounded up), which is all a pixel without weight of
    its own needs: its value comes from level 1 or coarser; 0 where nothing has weight."""
    a = np.ascontiguousarray(values * weight[..., None], dtype=np.float32)
    b = np.ascontiguousarray(weight, dtype=np.float32)
    means, confidences = [], []
    for level in range(levels):
        if level >= finest:
            means.append(a / np.maximum(b, 1e-6)[..., None])
            confidences.append(np.clip(b / FILL_WEIGHT, 0.0, 1.0))
        if min(b.shape) < 8:
            break
        a, b = np.asarray(cv2.pyrDown(a), np.float32), np.asarray(cv2.pyrDown(b), np.float32)
        if a.ndim == 2:  # OpenCV drops a single channel
            a = a[..., None]
    filled = means[-1] * (confidences[-1] > 0)[..., None]
    for mean, conf in zip(reversed(means[:-1]), reversed(confidences[:-1]), strict=True):
        up = cv2.resize(filled, (conf.shape[1], conf.shape[0]), interpolation=cv2.INTER_LINEAR)
        if up.ndim == 2:
            up = up[..., None]
        filled = conf[..., None] * mean + (1.0 - conf[..., None]) * up
    return filled.astype(np.float32)


def intensity_change(
    image: np.ndarray,
    codes: np.ndarray,
    valid: np.ndarray,
    classes: np.ndarray,
    params: AppearanceParams = _DEFAULTS,
    registration_px: int = 0,
) -> np.ndarray:
    """``A_p`` of the module docstring for one view.

    image : (H, W, 3) uint8 RGB. codes : (H, W) uint8 intensity codes of the old cloud as
    the view sees it (one channel of ``ViewSurface.colour`` built from
    :func:`intensity_codes`). valid : (H, W) bool, pixels with a surface. classes : (H, W)
    uint8 role raster. registration_px : r, the pose error tolerated. Returns (H, W) float32
    in [0, 1], 0 off the inventory pixels that have a surface.
    """
    out = np.zeros(valid.shape, dtype=np.float32)
    checked = in_roles(classes, params.classes)
    objects = checked & valid
    if not objects.any():
        return out
    width = valid.shape[1]
    close_px = close_width_px(params, width)
    if params.gap_px > 0:
        checked = footprint(
            classes, params.classes, close_px, ~valid, params.hole_reach, params.hole_classes
        )
    # the surroundings' colour is smooth: it is taken on f × f blocks (cost: docs/DECISIONS.md)
    f = max(1, int(round(width / WORK_WIDTH_PX)))
    grow = 2 * (registration_px + int(round(scale_px(params.intensity_margin_px, width))))
    grow = (grow // f) | 1
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (grow, grow))
    around = (cv2.dilate(_shrink(checked.astype(np.float32), f), disc) == 0).astype(np.float32)
    rows, cols = np.nonzero(objects)
    # the objects are outside ``around``: their values come from pyramid level 1 or coarser
    at = (
        np.minimum(rows // (2 * f), (around.shape[0] - 1) // 2),
        np.minimum(cols // (2 * f), (around.shape[1] - 1) // 2),
    )
    background = fill_from(_shrink(image.astype(np.float32), f), around, finest=1)[at]  # (N, 3)
    distance = np.sqrt(((image[rows, cols].astype(np.float32) - background) ** 2).sum(axis=-1))
    d0, d1 = params.intensity_same_rgb, params.intensity_differ_rgb
    same = np.clip((d1 - distance) / max(d1 - d0, 1e-6), 0.0, 1.0)
    if params.intensity_contrast > 0:
        same *= _contrast_gate(codes, valid, around, objects, at, f, params.intensity_contrast)
    out[rows, cols] = same
    if registration_px > 0:
        square = np.ones((2 * registration_px + 1, 2 * registration_px + 1), np.uint8)
        return np.asarray(cv2.morphologyEx(out, cv2.MORPH_OPEN, square), dtype=np.float32)
    return out


def _shrink(a: np.ndarray, f: int) -> np.ndarray:
    """``a`` (H, W) or (H, W, C) float32 averaged over f × f blocks (H // f, W // f, …)."""
    if f == 1:
        return a
    h, w = a.shape[0] // f, a.shape[1] // f
    small = cv2.resize(a[: h * f, : w * f], (w, h), interpolation=cv2.INTER_AREA)
    return small[..., None] if a.ndim == 3 and small.ndim == 2 else small


def _contrast_gate(
    codes: np.ndarray,
    valid: np.ndarray,
    around: np.ndarray,
    objects: np.ndarray,
    at: tuple[np.ndarray, np.ndarray],
    f: int,
    contrast: float,
) -> np.ndarray:
    """(N,) float32 in [0, 1] for the N pixels of ``objects`` (row-major): the mean
    log-intensity contrast of each pixel's object (8-connected piece) to its surroundings
    with a surface, over ``contrast``, capped at 1 (1 everywhere when no pixel around has a
    surface to compare with). ``around`` (the surroundings) is on f × f blocks, ``at`` the
    objects' pixels at pyramid level 1 of those."""
    log_i = codes.astype(np.float32) * np.float32(LN_PER_CODE)
    has = _shrink(valid.astype(np.float32), f)
    weight = around * (has > 0)
    if not weight.any():
        return np.ones(len(at[0]), np.float32)
    mean_log = _shrink(log_i * valid, f) / np.maximum(has, 1e-6)  # over the pixels with one
    behind = fill_from(mean_log[..., None], weight, finest=1)[..., 0][at]
    per_pixel = np.abs(log_i[objects] - behind)
    labels, n = ndimage.label(objects, structure=np.ones((3, 3), bool))
    lab = labels[objects]
    mean = np.bincount(lab, per_pixel, n + 1) / np.maximum(np.bincount(lab, minlength=n + 1), 1)
    return np.clip(mean[lab] / contrast, 0.0, 1.0).astype(np.float32)
