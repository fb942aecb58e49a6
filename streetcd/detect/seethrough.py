"""See-through objects (not in the paper; issue 16): does a railing still let its background
show through?

A railing in the old cloud is a few pixels of its class (its bars) in a footprint
(:func:`streetcd.detect.appearance.footprint`) that is mostly what stands behind it, seen through
the gaps, or holes where the surface filters dropped the triangles between a bar and the wall
2 m behind. When a hedge (or a board, a parked van) stands where the railing stood, none of
the other cues sees it without reference colours: eq. 5 compares single pixels, and foliage
re-projected through any wrong depth matches foliage a few pixels away; the texture cue's
windows need half their pixels on the old surface, which a railing's footprint does not have.

The test is the texture cue (:func:`streetcd.detect.texture.texture_change`) over the footprint
under two hypotheses of the old scene, each filling the whole footprint:

* the *plane*: the footprint as one opaque surface at the depth of the nearest pixel of the
  object's own surface (a railing still standing, in front of a plain wall);
* *behind*: the footprint at the depth of the nearest surface pixel that is not the object's
  (what its gaps show)::

    S_p = min(T_plane(p), T_behind(p))

An opaque, textured object where the railing stood is explained by neither hypothesis: it is
in front of the wall and, where it is not on the railing's line, off the plane too. A railing
still standing is explained by one of them, but only at a coarser scale than its bars: they
are a grating a few pixels in period that no single depth lines up together with the wall
behind. Both images are therefore low-passed first, with a Gaussian of
``σ = blur_m · f / z`` px (``z`` the object's median depth over its connected footprint, ``f``
the focal length in px): the grating goes, the wall's larger structure (windows, plinths,
lawn edges) stays, and so does the parallax of a hedge's leaves. The low-pass also stands in
for the texture cue's search over shifts (``registration_tolerance_px``): a registration
error up to about σ leaves blurred windows correlated, and each neighbour is still aligned
by its whole-image shift first (``max_global_shift_px``), so the windows are compared in
place, at a twenty-fifth of the search's cost on a 2 MP view. The blur is done where the cue
compares the windows: each image is shrunk once to the cue's working size
(:func:`~streetcd.detect.texture.work_size`) and blurred there, per group of footprints.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence

import cv2
import numpy as np

from streetcd.config import TextureParams
from streetcd.detect.appearance import fill_nearest
from streetcd.detect.boxes import mask_box
from streetcd.detect.correlate import NeighbourView
from streetcd.detect.texture import low_pass, shrunk_grey, texture_change, work_size
from streetcd.types import Intrinsics, Pose

BLUR_STEP = 1.25
"""Footprints whose blur differs by less than this factor share one low-pass (and one pass of
the texture cue): at most a few passes per view."""


def see_through_change(
    image_p: np.ndarray,
    depth_p: np.ndarray,
    own: np.ndarray,
    valid: np.ndarray,
    inside: np.ndarray,
    intrinsics_p: Intrinsics,
    pose_p: Pose,
    neighbours: Sequence[NeighbourView],
    params: TextureParams,
    occlusion_tolerance_m: float,
    reach_px: int,
    min_blur_px: float = 0.0,
) -> np.ndarray:
    """``S_p`` of the module docstring for view ``p``: (H, W) float32 in [0, 1], 0 outside
    ``inside`` and in footprints without a pixel of the object's own surface.

    image_p : (H, W, 3) uint8 RGB or (H, W) grey levels (uint8 or float32). depth_p : (H, W)
    float32 metres, the view's old surface (NaN = none). own : (H, W) bool, the pixels of the
    see-through object's own surface. valid : (H, W) bool, pixels with a surface. inside :
    (H, W) bool, the object's footprint.
    neighbours : as :func:`~streetcd.detect.texture.texture_change`'s; their hole depths
    (``holes``) are not used: they take the smallest depth around a hole, which at a
    railing's footprint is the pavement in front of it, and would hide the plane and what is
    behind it alike. reach_px : how far from a footprint's holes their fill looks for a depth
    (its gap width; :func:`~streetcd.detect.appearance.fill_nearest`). min_blur_px : the
    low-pass's smallest σ in px at the working size (our addition): a footprint whose metric
    blur is less is blurred this much (0: the metric blur alone).
    """
    out = np.zeros(depth_p.shape, np.float32)
    if not own.any() or not inside.any():
        return out
    plane = fill_nearest(depth_p, own, inside, reach_px)
    behind = fill_nearest(depth_p, valid & ~own, inside, reach_px)
    # every image shrunk once to the texture cue's working size, where it compares them, and
    # low-passed there per group: a 12 MP image shrinks in tens of milliseconds, a blur of
    # the shrunk copy in one or two
    view = shrunk_grey(image_p, work_size(params, depth_p.shape))
    shrunk = [_shrunk(nb, params) for nb in neighbours]
    for sigma, where in blur_groups(
        inside, own, depth_p, intrinsics_p.fx, params.see_through_blur_m
    ):
        view_lp = low_pass(view, max(min_blur_px, sigma * view.shape[1] / depth_p.shape[1]))
        blurred = [
            (low_pass(g, max(min_blur_px, sigma * g.shape[1] / width)), depth, intr, pose, None)
            for g, width, depth, intr, pose in shrunk
        ]
        t_plane, t_behind = (
            texture_change(
                view_lp,
                depth,
                intrinsics_p,
                pose_p,
                blurred,
                params,
                occlusion_tolerance_m,
                0.0,  # no window search: the low-pass tolerates as much (module docstring)
                where,
            )[0]
            for depth in (plane, behind)
        )
        np.maximum(out, np.minimum(t_plane, t_behind), out=out, where=where)
    return out


def _shrunk(
    neighbour: NeighbourView, params: TextureParams
) -> tuple[np.ndarray, int, np.ndarray, Intrinsics, Pose]:
    """A neighbour (image, depth, intrinsics, pose, holes) as the see-through test warps it:
    (grey levels, the image's full width, depth, intrinsics, pose), all at the texture cue's
    working size for the neighbour's own size (:func:`~streetcd.detect.texture.work_size`);
    its hole depths are left out (:func:`see_through_change`)."""
    image, depth, intrinsics, pose, _ = neighbour
    size = work_size(params, depth.shape)
    g = shrunk_grey(image, size)
    if (size[1], size[0]) != depth.shape:
        depth = cv2.resize(depth, size, interpolation=cv2.INTER_NEAREST)
        intrinsics = intrinsics.scaled(size[0] / intrinsics.width)
    return g, int(np.shape(image)[1]), depth, intrinsics, pose


def blur_groups(
    inside: np.ndarray, own: np.ndarray, depth: np.ndarray, focal_px: float, blur_m: float
) -> Iterator[tuple[float, np.ndarray]]:
    """(σ px, (H, W) bool) per group of the 8-connected pieces of the footprint ``inside``
    whose blur ``σ = blur_m · focal_px / z`` (``z`` the median ``depth`` (H, W) float32 metres of
    the piece's ``own`` pixels) lies within one ``BLUR_STEP`` bin; pieces without an own pixel
    are left out."""
    box = mask_box(inside)
    if box is None:
        return
    # labelled within the footprint's bounding box (a railing's strip, not the whole image)
    n, labels = cv2.connectedComponents(np.ascontiguousarray(inside[box], np.uint8), connectivity=8)
    if n <= 1:
        return
    has = own[box] & np.isfinite(depth[box])
    lab = labels[has]
    z = depth[box][has]
    bins: dict[int, list[int]] = {}
    sigmas: dict[int, float] = {}
    for k in np.unique(lab):
        sigma = blur_m * focal_px / float(np.median(z[lab == k]))
        b = round(np.log(max(sigma, 1e-3)) / np.log(BLUR_STEP))
        bins.setdefault(b, []).append(int(k))
        sigmas[b] = BLUR_STEP**b if blur_m > 0 else 0.0
    for b, members in sorted(bins.items()):
        chosen = np.zeros(n, bool)
        chosen[members] = True
        where = np.zeros(inside.shape, bool)
        where[box] = chosen[labels]
        yield sigmas[b], where
