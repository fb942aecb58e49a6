"""Reference-colour check: is the object the old cloud shows still what the image shows?

**Not in the paper.** Eq. 5 compares the view with its *new* neighbours re-projected through the
*old* surface, so it sees a change only where the geometry changed *and* the colours along the
wrong rays differ. Two kinds of change slip through it (the paper's own caveat: "for
homogeneous areas, geometrical changes may not lead to color differences"):

* a removed object in front of a plain wall: every neighbour, sampled through the board's old
  depth, shows the same plaster the view shows;
* an object replaced by another at the same place (a hedge where a railing stood): the new
  object is photo-consistent with the old geometry.

The MLS cloud carries colours (the paper's z-buffer of eq. 2 already relies on them), so the
view can also be compared with the *old appearance* itself: the surface rasteriser gives
each pixel the colour of its nearest kept point (:class:`streetcd.detect.surface.ViewSurface`
``colour``). Old and new colours come from different sensors and days, so they are
compared after

1. **colour transfer**: each channel of the reference colours is moved onto the image's
   mean and standard deviation over the pixels that have a surface (a gain and an offset
   per channel, :func:`transfer_colours`; ``AppearanceParams.transfer = "log"`` fits them to
   ``ln(1 + level)`` instead, an exposure and a gamma): exposure, white balance and the
   scanner camera's response cancel;
2. **an illumination-tolerant distance**: the L1 difference of chromaticities
   ``(rgb + ε/3) / (R + G + B + ε)`` (0–2), plus the log-brightness difference beyond a
   tolerance, so cast shadows (darker, same hue) that the scan did not have count little:
   ``A_p = min(1, w_c · ‖ĉ_I − ĉ_M‖₁ + w_b · max(0, |ln(ΣI / ΣM)| − t_b))``. The ε keeps
   the chromaticity of dark pixels from noise by drawing it towards grey
   (``AppearanceParams.dark_grey``; ``rgb / (R + G + B + ε)`` before, which drew it towards
   0, so that a dark colour differed from every lit one in chroma).
3. optionally, **the nearer of two references** (``AppearanceParams.raw_reference``, off by
   default): ``A_p`` is the smaller of the distances to the transferred colour and to the
   colour as the cloud stored it. The transfer is fitted to the whole view's means and
   spreads; where they differ much from the cloud's, its offset takes a dark channel to 0
   and makes up a hue (a black railing seen against a bright street became cyan). On, it
   halves some false alarms and loses the removed objects that were found only through
   such a made-up hue (docs/TUNING.md, thirty-seventh round).

It is checked on the **inventory classes** (poles, signs, railings, furniture), over their
footprint with see-through gaps closed (a railing's bars are a few pixels wide; the hedge
that replaced it stands in the gaps too, where the old surface is the wall behind): there
the question is whether the object is still there. Façades and trees differ from their scan
for reasons that are no change (glass reflects the sky, foliage moves, balconies cast
shadows the scan did not have), and new objects in front of them are left to eq. 5, which
sees them by their geometry. The **ground** is checked as well
(``AppearanceParams.ground_classes``, which :func:`streetcd.detect.chain.fuse_appearance`
adds to the classes) where the cloud has colours and tells its road from its ground: a bench
or a bin added on the pavement stands little in front of it, so eq. 5, low-weighted there,
sees almost nothing (docs/TUNING.md, thirtieth round). The road is not checked: cars come
and go on it. The **vegetation and the façades below the camera's height** are checked by
their hue alone (``AppearanceParams.hue_classes``, the ``by_hue`` pixels of
:func:`appearance_change`; :func:`streetcd.detect.chain.fuse_appearance` picks them), the
reference white-balanced by a gain per channel (:func:`white_balance_luts`): a bench or a
board in front of a hedge or a wall differs from it in hue, which eq. 5 misses (its low
weight on vegetation, a wall as dark as the bench), while foliage's shading and a
balcony's cast shadow differ from the scan's in brightness, for no change (docs/TUNING.md,
thirty-fifth round). Without a brightness term there, a dark colour keeps ε on the sum, its
chromaticity drawn towards 0: a dark bench before a lit plinth differs from it in nothing
else (thirty-sixth round). :func:`streetcd.detect.chain.detect_view` fuses
``max(C_p, k · A_p)`` before the node energy of eq. 7; ``AppearanceParams(enabled=False)``
is the paper's method.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from streetcd.config import AppearanceParams, scale_px
from streetcd.detect.boxes import mask_box
from streetcd.detect.roles import in_roles
from streetcd.errors import InputError

_DEFAULTS = AppearanceParams()
_NEAREST = cv2.INTER_NEAREST_EXACT  # integer upscaling: each block's value on its f × f pixels
CLOSE_WORK_PX = 16  # the footprint's closing runs on blocks where its disc is about this wide
STAT_STRIDE = 4  # colour statistics on every 4th row and column: 1/16 of the pixels suffice


def transfer_luts(
    reference: np.ndarray, image: np.ndarray, valid: np.ndarray, model: str = "linear"
) -> np.ndarray:
    """(3, 256) uint8 tables moving the reference colours channel by channel onto the image's
    mean and standard deviation over ``valid`` pixels (Reinhard et al. 2001, per RGB
    channel): a gain and an offset per channel, which exposure, white balance and the
    scanner camera's response need, and which a changed object covering a few per cent of
    the view cannot absorb (a histogram match would map its colours onto whatever the image
    has most of). The statistics are taken on every ``STAT_STRIDE``-th row and column.

    model : "linear", the gain and offset on the levels (Reinhard's), or "log", on
    ``ln(1 + level)`` (:func:`channel_map`). reference, image : (H, W, 3) uint8; valid :
    (H, W) bool. Identity tables when no pixel is valid.
    """
    pick, k = _statistics_grid(valid)
    luts = np.tile(np.arange(256, dtype=np.uint8), (3, 1))
    if not pick.any():
        return luts
    ref = reference[::k, ::k][pick].astype(np.float64)  # (N, 3)
    img = image[::k, ::k][pick].astype(np.float64)
    for c in range(3):
        luts[c] = np.clip(np.round(channel_map(ref[:, c], img[:, c], model)), 0, 255)
    return luts


def _statistics_grid(valid: np.ndarray) -> tuple[np.ndarray, int]:
    """``(pick, k)``: the pixels of ``valid`` on every ``k``-th row and column that colour
    statistics are taken from, ``k = STAT_STRIDE``, or ``k = 1`` (all of ``valid``) where that
    grid misses every valid pixel (a thin object in a small view)."""
    pick = valid[::STAT_STRIDE, ::STAT_STRIDE]
    if pick.any():
        return pick, STAT_STRIDE
    return valid, 1


def channel_map(reference: np.ndarray, image: np.ndarray, model: str = "linear") -> np.ndarray:
    """(256,) float64: where each level of one channel of the reference goes, given that
    channel's samples (N,) float64 of the reference and of the image at the same pixels.

    "linear": ``(x − μ_M) · σ_I / σ_M + μ_I``. "log": the same on ``ln(1 + x)``, i.e.
    ``1 + y = e^b (1 + x)^g``, an exposure and a gamma: two cameras' responses differ by a
    power law, and the linear map's offset can take a channel's dark levels to 0, a change of
    chromaticity on a dark object that is still there (docs/TUNING.md, twentieth round).
    """
    levels = np.arange(256, dtype=np.float64)
    if model == "log":
        lr, li = np.log1p(reference), np.log1p(image)
        gain = li.std() / max(lr.std(), 1e-3)
        return np.expm1((np.log1p(levels) - lr.mean()) * gain + li.mean())
    if model != "linear":
        raise InputError(f"colour transfer model {model!r} must be 'linear' or 'log'")
    gain = image.std() / max(reference.std(), 1.0)
    return (levels - reference.mean()) * gain + image.mean()


def transfer_colours(
    reference: np.ndarray, image: np.ndarray, valid: np.ndarray, model: str = "linear"
) -> np.ndarray:
    """The whole (H, W, 3) uint8 reference through :func:`transfer_luts`."""
    luts = transfer_luts(reference, image, valid, model)
    return np.stack([cv2.LUT(reference[..., c], luts[c]) for c in range(3)], axis=-1)


def white_balance_luts(reference: np.ndarray, image: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """(3, 256) uint8 tables scaling each channel of the reference by ``mean(I_c) / mean(M_c)``
    over ``valid`` pixels (a von Kries white balance, every ``STAT_STRIDE``-th row and column):
    gains without an offset, so a dark colour keeps its hue, which the gain and offset of
    :func:`transfer_luts` do not keep (an offset of a few levels turns dark green grey).
    Identity tables when no pixel is valid."""
    pick, k = _statistics_grid(valid)
    levels = np.arange(256, dtype=np.float64)
    if not pick.any():
        return np.tile(levels.astype(np.uint8), (3, 1))
    mask = pick.astype(np.uint8)  # OpenCV's masked mean: a tenth of numpy's gather and mean
    ref = np.array(cv2.mean(np.ascontiguousarray(reference[::k, ::k]), mask=mask)[:3])
    img = np.array(cv2.mean(np.ascontiguousarray(image[::k, ::k]), mask=mask)[:3])
    gains = img / np.maximum(ref, 1.0)
    return np.clip(np.round(levels[None, :] * gains[:, None]), 0, 255).astype(np.uint8)


def colour_distance(
    image: np.ndarray, reference: np.ndarray, params: AppearanceParams = _DEFAULTS
) -> np.ndarray:
    """``A`` of the module docstring, per pixel, without masking. image, reference :
    (H, W, 3) uint8 (reference already transferred). Returns (H, W) float32 in [0, 1]."""
    i = image.astype(np.float32)
    m = reference.astype(np.float32)
    # channels added one by one, not summed over the last axis: the same float32 sums,
    # without numpy's slow reduction over an axis of three (a third of the check's time)
    si = i[..., 0] + i[..., 1] + i[..., 2] + np.float32(params.dark_level)  # the brightness
    sm = m[..., 0] + m[..., 1] + m[..., 2] + np.float32(params.dark_level)  # either way
    if params.dark_grey:  # ε/3 on each channel: a dark colour's chromaticity tends to grey
        i += np.float32(params.dark_level / 3)  # (without: it tends to 0, a colour of its own)
        m += np.float32(params.dark_level / 3)
    gap = i / si[..., None]
    gap -= m / sm[..., None]
    np.abs(gap, out=gap)
    chroma = gap[..., 0] + gap[..., 1] + gap[..., 2]
    bright = np.maximum(np.abs(np.log(si / sm)) - np.float32(params.brightness_tolerance), 0)
    a = params.chroma_weight * chroma + params.brightness_weight * bright
    return np.clip(a, 0.0, 1.0).astype(np.float32)


def reference_distance(
    image_px: np.ndarray,
    reference_px: np.ndarray,
    luts: np.ndarray,
    params: AppearanceParams = _DEFAULTS,
) -> np.ndarray:
    """:func:`colour_distance` of image colours (N, 3) uint8 from reference colours (N, 3)
    uint8 moved through the transfer tables ``luts`` (3, 256) of :func:`transfer_luts`."""
    if len(reference_px) == 0:
        return np.zeros(0, np.float32)
    # one OpenCV look-up through the three tables at once (luts[c][reference_px[:, c]])
    tables = np.ascontiguousarray(np.asarray(luts, np.uint8).T).reshape(256, 1, 3)
    mapped = cv2.LUT(np.ascontiguousarray(reference_px, np.uint8).reshape(-1, 1, 3), tables)
    return colour_distance(image_px, mapped.reshape(-1, 3), params)


def footprint(
    classes: np.ndarray,
    checked_classes: tuple[int, ...],
    close_px: int,
    holes: np.ndarray | None = None,
    hole_reach: float = 0.0,
    hole_classes: tuple[int, ...] = (),
) -> np.ndarray:
    """(H, W) bool: the pixels of ``checked_classes`` in the (H, W) uint8 class raster, closed
    (dilated, then eroded) with a disc ``close_px`` wide, so that the see-through gaps of a
    railing or between a sign's posts count as the object's footprint.

    holes : (H, W) bool, pixels without a surface. Those within ``hole_reach · close_px`` of
    the class count as the class before the closing: the surface filters drop the triangles
    between a railing's thin bars and the wall behind them, so a railing is mostly holes
    with a few pixels of its class, and gaps wider than the disc would stay open.
    hole_classes : only holes near those of ``checked_classes`` that are among these roles
    count (empty: near any of ``checked_classes``); a role not checked brings no holes.
    """
    mask = in_roles(classes, checked_classes)
    if close_px <= 1 or not mask.any():
        return mask
    # OpenCV's closing with a full-resolution disc is slow at 12 MP; on a grid of f × f blocks
    # (any pixel of the class marks its block) a disc of about CLOSE_WORK_PX is cheap
    # (docs/BENCHMARKS.md).
    # The footprint then reaches up to f − 1 px past the object, onto what is behind it,
    # whose reference colour is its own: no change is made up there.
    f = max(1, close_px // CLOSE_WORK_PX)
    small = _block_any(mask, f)
    k = max(3, close_px // f) | 1
    if holes is not None and hole_reach > 0:
        r = max(3, int(hole_reach * close_px / f)) | 1
        source = small
        if hole_classes:
            roles = tuple(c for c in checked_classes if c in hole_classes)
            source = _block_any(in_roles(classes, roles), f)
        near = cv2.dilate(source, cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (r, r)))
        small |= near & _block_any(holes, f)
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    closed = cv2.morphologyEx(small, cv2.MORPH_CLOSE, disc)
    h, w = mask.shape
    if f == 1:
        return mask | (closed > 0)
    big = cv2.resize(closed, (closed.shape[1] * f, closed.shape[0] * f), interpolation=_NEAREST)
    return mask | (big[:h, :w] > 0)


def close_width_px(params: AppearanceParams, width: int) -> int:
    """The odd width in px of the disc that closes an object's footprint (:func:`footprint`)
    in an image ``width`` px wide: ``params.gap_px`` scaled from ``REFERENCE_WIDTH_PX``."""
    return int(round(scale_px(params.gap_px, width))) | 1


def _block_any(mask: np.ndarray, f: int) -> np.ndarray:
    """(ceil(H/f), ceil(W/f)) uint8: 1 where any pixel of the f × f block of ``mask`` is set
    (an f × f dilation anchored at the block's corner, read at every f-th pixel: OpenCV's
    separable max is much faster than numpy's max over the reshaped blocks,
    docs/BENCHMARKS.md)."""
    if f == 1:
        return mask.astype(np.uint8)
    h, w = mask.shape
    hb, wb = -(-h // f), -(-w // f)
    blocks = np.zeros((hb * f, wb * f), np.uint8)
    blocks[:h, :w] = mask
    grown = cv2.dilate(blocks, np.ones((f, f), np.uint8), anchor=(0, 0), borderValue=0)
    return np.ascontiguousarray(grown[::f, ::f])


def fill_nearest(
    reference: np.ndarray, valid: np.ndarray, where: np.ndarray, reach_px: int = 0
) -> np.ndarray:
    """``reference`` (H, W, 3) (or any (H, W, …) raster: colours, depths) with each pixel of
    ``where`` that has no surface (``valid`` False) given the value of the nearest pixel that
    has one (a distance transform with nearest-pixel labels, OpenCV's 5×5 L2 mask).
    ``reach_px`` > 0 looks for that pixel only within the holes' bounding box grown by
    ``reach_px`` (a gap's own width suffices); 0 looks everywhere."""
    holes = where & ~valid
    if not holes.any() or not valid.any():
        return reference
    # the holes' box grown by the reach (never None: there are holes), or the whole image
    grown = (mask_box(holes, reach_px) if reach_px > 0 else None) or np.s_[:, :]
    box = valid[grown]
    if not box.any():
        return reference
    _, labels = cv2.distanceTransformWithLabels(
        (~box).astype(np.uint8), cv2.DIST_L2, 5, labelType=cv2.DIST_LABEL_PIXEL
    )
    # labels number the box's valid pixels 1, 2, … in row-major order
    source = np.flatnonzero(box.ravel())
    box_holes = holes[grown]
    out = reference.copy()
    pick = source[labels[box_holes] - 1]
    flat = reference[grown].reshape((-1, *reference.shape[2:]))
    out[grown][box_holes] = flat[pick]
    return out


def appearance_change(
    image: np.ndarray,
    reference: np.ndarray,
    valid: np.ndarray,
    classes: np.ndarray,
    params: AppearanceParams = _DEFAULTS,
    registration_px: int = 0,
    by_hue: np.ndarray | None = None,
) -> np.ndarray:
    """Appearance change ``A_p`` (module docstring) of one view.

    image : (H, W, 3) uint8 RGB of the view. reference : (H, W, 3) uint8 colours of the old
    cloud as the view sees it (``ViewSurface.colour``). valid : (H, W) bool, pixels with a
    surface. classes : (H, W) uint8 class raster. Returns (H, W) float32 in [0, 1], 0 outside
    the footprint of ``params.classes`` (:func:`footprint`, its gaps closed over
    ``params.gap_px`` scaled to the image width); gaps without a surface take the nearest
    surface pixel's colour. registration_px > 0: ``A_p`` is opened (a grey erosion, then a
    dilation) with a (2r+1)² square, so the bands that a registration error of up to ``r``
    px leaves along an object's outline (image and reference shifted against each other)
    go, while anything wider keeps its extent: the tolerance eq. 5 has through
    :func:`streetcd.detect.correlate.colour_envelope`.

    by_hue : (H, W) bool or None, pixels to check as well by their hue (with a surface,
    outside the footprint: vegetation, façades): there ``A_p`` is the chromaticity term
    alone, the reference white-balanced (:func:`white_balance_luts`), not transferred:
    shading and cast shadows change brightness, not hue, and a bench or a board in front of
    a hedge or a wall differs from it in hue.
    """
    close_px = close_width_px(params, valid.shape[1])
    checked = (
        footprint(
            classes,
            params.classes,
            close_px,
            holes=~valid,
            hole_reach=params.hole_reach,
            hole_classes=params.hole_classes,
        )
        if params.gap_px > 0
        else None
    )
    if checked is None:
        checked = valid & in_roles(classes, params.classes)
    out = np.zeros(valid.shape, dtype=np.float32)
    hued = None if by_hue is None else by_hue & valid & ~checked
    if not valid.any() or not (checked.any() or (hued is not None and hued.any())):
        return out
    if checked.any():
        luts = transfer_luts(reference, image, valid, params.transfer)
        ref = fill_nearest(reference, valid, checked, close_px)[checked]  # (N, 3) where checked
        seen = image[checked]  # (N, 3)
        distance = reference_distance(seen, ref, luts, params)
        if params.raw_reference:  # the stored colour as well: the transfer can make up a hue
            np.minimum(distance, colour_distance(seen, ref, params), out=distance)
        out[checked] = distance
    if hued is not None and hued.any():
        # no brightness term here, so darkness stays a colour of its own (ε on the sum): a
        # dark bench before a lit plinth differs from it in nothing else
        hue_only = replace(params, brightness_weight=0.0, dark_grey=False)
        balance = white_balance_luts(reference, image, valid)
        out[hued] = reference_distance(image[hued], reference[hued], balance, hue_only)
    if registration_px > 0:
        square = np.ones((2 * registration_px + 1, 2 * registration_px + 1), np.uint8)
        return np.asarray(cv2.morphologyEx(out, cv2.MORPH_OPEN, square), dtype=np.float32)
    return out
