"""One view end to end (paper §3.2–3.4): the only module that chains the steps.

:func:`detect_view` is the pure kernel (arrays in, :class:`DetectionResult` out):

1. surface of the view and of each neighbour from the reference cloud (z-buffer eq. 1–3,
   view-dependent triangulation; :func:`streetcd.detect.surface.surface_for_view`);
2. histogram stretching of every image, each neighbour's registration shift against the view
   (not in the paper; :mod:`streetcd.detect.align`) and the raw change ``C_p`` (eq. 4–5,
   :mod:`streetcd.detect.correlate`), fused with the reference-colour check ``A_p`` (not in the
   paper; :mod:`streetcd.detect.appearance`) as ``max(C_p, k · A_p)``;
3. node energy (eq. 7), class-aware superpixels (eq. 10–11), graph cut (eq. 6, 8–9) and
   speckle filter (:mod:`streetcd.detect.graphcut`);
4. each changed region's outline redrawn at pixel level by colour, within half a superpixel
   of the cut's (not in the paper; :mod:`streetcd.detect.refine`), and the speckle filter again;
5. the changed regions: 8-connected components of the mask, each with a score (mean node
   energy), its 3D centroid and extent from the depth raster and the dominant class
   (:mod:`streetcd.detect.regions`).

Nothing here reads or writes files: images, clouds and outputs are :mod:`streetcd.io`'s, and
what may be kept between calls (:class:`~streetcd.detect.cache.SurfaceCache`) is passed in.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from streetcd.config import AppearanceParams, DetectParams, TextureParams, scale_px
from streetcd.detect.align import neighbour_shifts
from streetcd.detect.appearance import (
    appearance_change,
    close_width_px,
    footprint,
    reference_distance,
    transfer_luts,
)
from streetcd.detect.cache import SurfaceCache, cloud_rgb8, wants_colour
from streetcd.detect.correlate import (
    Neighbour,
    NeighbourView,
    camera_rays,
    envelope_levels,
    hole_depths,
    pair_lut,
    pinhole_axes,
    raw_change,
    registration_radius_px,
    stretch_lut,
    weigh_low_classes,
)
from streetcd.detect.graphcut import (
    cut_changes,
    nearest_index,
    node_energy,
    superpixel_mean,
    superpixels,
)
from streetcd.detect.intensity import intensity_change, intensity_codes
from streetcd.detect.locate import Working, region_depth_fractions, working_set
from streetcd.detect.refine import refined_mask
from streetcd.detect.regions import Region, changed_regions, cut_apart
from streetcd.detect.roles import (
    cloud_roles,
    in_roles,
    infers,
    mostly_roleless,
    road_told,
    useless_classes,
)
from streetcd.detect.seethrough import see_through_change
from streetcd.detect.silhouette import GROUND_ROLES, near_depth_hypothesis
from streetcd.detect.surface import ViewSurface, surface_for_view
from streetcd.detect.sweep import nearer_depth_change
from streetcd.detect.texture import (
    WorkingView,
    grey_u8,
    near_layer,
    texture_change,
    working_view,
)
from streetcd.errors import (
    EmptyViewError,
    InputError,
)
from streetcd.types import Intrinsics, PointCloud, View

_DEFAULTS = DetectParams()  # frozen: one shared default instance
log = logging.getLogger(__name__)
CHANGE_CELL_PX = 24.0  # raw change runs where a superpixel cell is about this wide
# The point arrays a detection reads besides xyz and classification: never gps_time, which
# a crop for the detector need not decompress (a fifth of a tile's bytes).
CLOUD_FIELDS = ("intensity", "rgb")


@dataclass(frozen=True)
class DetectionResult:
    """Everything :func:`detect_view` found in one view, and what a reader needs to see why.

    mask : (H, W) bool, changed pixels. raw_change : (H, W) float32 ``C_p`` in [0, 1].
    node_energy : (H, W) float32 ``D_p(x_p = 0)`` of eq. 7 in [0, 1].
    superpixels : (H, W) int32 labels. depth : (H, W) float32 metres (NaN = no surface).
    classes : (H, W) uint8 (0 = no surface). regions : list of :class:`Region`.
    score : float in [0, 1], the highest region score (0 without regions).
    changed_fraction : share of the image's pixels in the mask. origin : (3,) float64 CRS
    metres of the local frame. Beyond the contract: ``region_labels`` (H, W) int32 (0 = none),
    ``support`` (H, W) uint8 (neighbours that gave evidence per pixel), ``view`` (name),
    ``neighbours`` (names of the neighbours used), ``timings`` (seconds per step),
    ``appearance`` (H, W) float32 ``A_p`` of :mod:`streetcd.detect.appearance` in [0, 1], or None
    when the check is off or the cloud has no colours. The node energy is eq. 7 of
    ``max(raw_change, weight · appearance)``. ``cut_mask`` (H, W) bool is the superpixel
    cut's mask before :mod:`streetcd.detect.refine` redrew its outlines (``mask`` when that is off).
    ``texture`` (H, W) float32 ``T_p`` of :mod:`streetcd.detect.texture` in [0, 1], or None when
    that cue is off; the node energy then sees ``max(…, texture.weight · T_p)``.
    """

    mask: np.ndarray
    raw_change: np.ndarray
    node_energy: np.ndarray
    superpixels: np.ndarray
    depth: np.ndarray
    classes: np.ndarray
    regions: list[Region]
    score: float
    changed_fraction: float
    origin: np.ndarray
    region_labels: np.ndarray
    support: np.ndarray
    view: str = ""
    neighbours: tuple[str, ...] = ()
    timings: dict[str, float] = field(default_factory=dict)
    appearance: np.ndarray | None = None
    cut_mask: np.ndarray | None = None
    texture: np.ndarray | None = None


def _check_image(image: np.ndarray, view: View) -> np.ndarray:
    image = np.asarray(image)
    intr = view.intrinsics
    if image.dtype != np.uint8 or image.shape != (intr.height, intr.width, 3):
        raise InputError(
            f"view {view.name!r}: image is {image.dtype} {image.shape}, the "
            f"camera expects uint8 ({intr.height}, {intr.width}, 3)"
        )
    return image


def view_surface_of(
    image: np.ndarray,
    local: View,
    cloud: PointCloud,
    params: DetectParams,
    cache: SurfaceCache | None = None,
    colours: Callable[[], np.ndarray | None] | None = None,
) -> ViewSurface:
    """The surface of the view ``local`` (local frame) from ``cache`` or built (and cached);
    EmptyViewError as :func:`streetcd.detect.surface.surface_for_view`. ``colours`` gives
    the cloud's 8-bit colours (:func:`cloud_colours`), converted once for all the surfaces of
    a call. The near points' fill (:func:`streetcd.detect.surface.fill_from_points`) needs
    the cloud's own classes: where its roles are inferred from the geometry, a lawn sign's
    sparse points taken for a pole filled into a false region of the real case's twin
    (docs/TUNING.md, thirty-first round)."""
    if colours is None:
        colours = cloud_colours(cloud, params, cache)

    def build() -> ViewSurface:
        roles = cloud_roles(cloud.xyz, cloud.classification, params.classes)
        fill = not infers(cloud.classification, params.classes)
        return surface_for_view(
            cloud.xyz, roles, image, local.intrinsics, local.pose, params, colours(), fill=fill
        )[0]

    if cache is None:
        return build()
    key = cache.key(image, local, cloud, params)
    surf = cache.get(key, cloud)
    if surf is None:
        surf = build()
        cache.put(key, cloud, surf)
    return surf


def cloud_colours(
    cloud: PointCloud, params: DetectParams, cache: SurfaceCache | None
) -> Callable[[], np.ndarray | None]:
    """A function giving the cloud's colours as (N, 3) uint8 for the z-buffer (eq. 2), or
    None when the appearance check is off or the cloud has none; converted on first call
    only (and kept by ``cache`` for the cloud's lifetime when one is given). A cloud without
    colours gives its intensity codes instead (:func:`streetcd.detect.intensity.intensity_codes`)
    with ``appearance.intensity`` (:func:`reference_kind` tells which)."""
    done: list[np.ndarray | None] = []

    def colours() -> np.ndarray | None:
        if not done:
            rgb = _rgb8_of(cloud, params, cache)
            if rgb is None and params.appearance.enabled and params.appearance.intensity:
                rgb = intensity_codes(cloud.intensity)
            done.append(rgb)
        return done[0]

    return colours


def _no_colours() -> None:
    return None


def detect_view(
    image: np.ndarray,
    view: View,
    neighbours: Sequence[tuple[np.ndarray, View]],
    cloud: PointCloud,
    params: DetectParams = _DEFAULTS,
    *,
    surfaces: SurfaceCache | None = None,
) -> DetectionResult:
    """Change mask of one view against the reference cloud (paper §3.2–3.4).

    image : (H, W, 3) uint8 RGB of ``view``. neighbours : (image, view) pairs of overlapping
    views (the paper uses 2–3). Views carry CRS poses; they are moved into the cloud's local
    frame (``view.local(cloud.origin)``). A neighbour that sees no point is left out.
    surfaces : where surfaces are looked up and kept (:class:`~streetcd.detect.cache.SurfaceCache`,
    owned by the caller: a worker keeps one for its run); None, the default, builds every
    surface afresh and keeps nothing. The result is the same either way; with a cache, the
    surfaces in it are shared with the cache and must not be modified.

    Raises EmptyViewError naming the view when it sees no reference point, InputError when an
    image does not fit its camera.
    """
    timings: dict[str, float] = {}
    clock = time.perf_counter()

    def lap(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        timings[name] = timings.get(name, 0.0) + now - clock
        clock = now

    image = _check_image(image, view)
    local = view.local(cloud.origin)
    _check_classes(cloud, params, surfaces)
    colours = cloud_colours(cloud, params, surfaces)
    try:
        surf = view_surface_of(image, local, cloud, params, surfaces, colours)
    except EmptyViewError as exc:
        raise EmptyViewError(f"view {view.name!r} sees no reference points: {exc}") from None
    if not surf.valid.any():
        raise EmptyViewError(
            f"view {view.name!r} sees no reference surface (points project but form no triangle)"
        )
    lap("surface")
    used: list[Neighbour] = []
    seen: list[NeighbourView] = []
    names: list[str] = []
    view_lut = stretch_lut(image, params.correlate.stretch_percentiles)
    # Only a neighbour's depth is read below: without a cache, where its surface is not kept
    # for its own turn as a view, its colour raster is not drawn.
    nb_colours = colours if surfaces is not None else _no_colours
    for nb_image, nb_view in neighbours:
        nb_image = _check_image(nb_image, nb_view)
        nb_local = nb_view.local(cloud.origin)
        try:
            nb_surf = view_surface_of(nb_image, nb_local, cloud, params, surfaces, nb_colours)
        except EmptyViewError:
            lap("surface")
            continue  # a neighbour without points gives no evidence
        lap("surface")
        used.append(_neighbour(nb_image, nb_surf, nb_local, surf, local, view_lut, image, params))
        seen.append((nb_image, nb_surf.depth, nb_local.intrinsics, nb_local.pose, used[-1].holes))
        names.append(nb_view.name)
        lap("stretch")
    stretched = cv2.LUT(np.ascontiguousarray(image), view_lut)  # = stretch_histogram(image)
    lap("stretch")
    # grey levels once per image (uint8): the alignment and the texture cue read them
    greys = None
    if used and (params.correlate.align_shift_px > 0 or params.texture.enabled):
        greys = _greys(image, seen)
    working = None  # the view and its neighbours at the texture cue's size, made once
    if params.correlate.align_shift_px > 0 and greys is not None:
        used, working = _aligned(used, greys, surf, local, params)
        lap("align")
    kind = reference_kind(cloud, params, surfaces) if surf.colour is not None else None
    gated = kind == "colour" and params.correlate.second_smallest_gate > 0
    change, support, minimum = _raw_change_at_cell_scale(
        stretched, surf.depth, surf.classes, local, used, params, keep_minimum=gated
    )
    if minimum is not None:
        change = gate_second_smallest(change, minimum, image, surf, local, params)
    if params.correlate.silhouette_margin_m > 0 and used:
        grey = _outline_grey(image, view_lut, params)
        change = _with_near_hypothesis(change, stretched, surf, local, used, params, grey)
    used.clear()  # their envelopes and depths (360 MB at 12 MP) are not needed past eq. 5
    lap("raw_change")
    if params.appearance.enabled and kind != "colour":
        _tell_no_colours(surfaces, kind)
    ground = kind == "colour" and road_told(cloud.classification, params.classes)
    inferred = infers(cloud.classification, params.classes)
    fused, appearance = fuse_appearance(
        image, surf, change, local, params, kind or "colour", ground=ground, inferred=inferred
    )
    if appearance is not None:
        lap("appearance")
    texture = None
    if params.texture.enabled and greys is not None:
        coloured = params.appearance.enabled and kind == "colour"
        texture = _texture(*greys, surf, local, params, working, coloured)
        fused = np.maximum(fused, np.float32(params.texture.weight) * texture)
        lap("texture")
    if params.correlate.nearer_weight > 0 and len(seen) >= 2:
        nearer = _nearer(image, surf, local, seen, params)
        fused = np.maximum(fused, np.float32(params.correlate.nearer_weight) * nearer)
        lap("nearer")
    labels = None
    if params.graphcut.energy_of_mean:  # eq. 7 of each superpixel's mean raw change
        labels = superpixels(stretched, surf.classes, params.graphcut)
        fused = superpixel_mean(fused, labels)
    energy = node_energy(fused, params.graphcut.a, params.graphcut.b)
    lap("node_energy")
    cut = cut_changes(energy, stretched, surf.depth, surf.classes, params.graphcut, labels=labels)
    lap("graphcut")
    mask = refined_mask(image, cut.mask, params)
    lap("refine")
    mask = cut_apart(mask, surf.classes, params.refine.apart_classes)
    region_labels, regions = changed_regions(
        mask, energy, surf.depth, surf.classes, local.intrinsics, local.pose
    )
    if regions and params.locate.enabled:  # most views have none: nothing to make small
        locating = _locating(image, surf, local, seen, params)
        if locating is not None:
            regions = _located(regions, region_labels, locating, local, params)
    seen.clear()
    lap("regions")
    score = max((r.score for r in regions), default=0.0)
    return DetectionResult(
        mask=mask,
        raw_change=change,
        node_energy=energy,
        superpixels=cut.superpixels,
        depth=surf.depth,
        classes=surf.classes,
        regions=regions,
        score=float(score),
        changed_fraction=float(mask.mean()),
        origin=np.asarray(cloud.origin, np.float64),
        region_labels=region_labels,
        support=support,
        view=view.name,
        neighbours=tuple(names),
        timings=timings,
        appearance=appearance,
        cut_mask=cut.mask,
        texture=texture,
    )


def fuse_appearance(
    image: np.ndarray,
    surf: ViewSurface,
    change: np.ndarray,
    local: View,
    params: DetectParams,
    kind: str = "colour",
    *,
    ground: bool = False,
    inferred: bool = False,
) -> tuple[np.ndarray, np.ndarray | None]:
    """The change eq. 7 sees, ``max(C_p, k · A_p)``, and ``A_p`` (:mod:`streetcd.detect.appearance`)
    of the view ``image`` (H, W, 3) uint8 on its surface ``surf``; ``(change, None)`` when the
    check is off or the surface has no colours. change : (H, W) float32 raw change. kind
    "intensity" (:func:`reference_kind`): ``surf.colour`` holds intensity codes, and ``A_p``
    is the intensity check's (:mod:`streetcd.detect.intensity`). ground: the colour check
    looks at ``appearance.ground_classes`` as well (:func:`detect_view` asks for it when the
    cloud has colours and tells its road from its ground, :func:`~streetcd.detect.roles.road_told`).
    inferred: the cloud's roles are inferred from its geometry (:func:`~streetcd.detect.roles.infers`):
    the holes join the footprint near any role, ``appearance.hole_classes`` left aside, since
    the near points' fill that closes a near pole is off then (:func:`view_surface_of`); an
    inferred pole is whatever stands upright, and its holes are the rest of it. Without this,
    the real case's twin through the nightly pipeline flagged a view
    (``tests/test_real_pipeline.py::test_the_real_unchanged_twin_reports_nothing``). With
    real colours, the ``appearance.hue_classes`` pixels below the camera
    (:func:`below_camera`) are checked by their hue as well."""
    if not params.appearance.enabled or surf.colour is None:
        return change, None
    radius = registration_radius_px(local.intrinsics.width, params.correlate)
    ap = params.appearance
    if inferred and ap.hole_classes:
        ap = replace(ap, hole_classes=())
    if kind == "intensity":
        appearance = intensity_change(
            image, surf.colour[..., 0], surf.valid, surf.classes, ap, radius
        )
    else:
        if ground and ap.ground_classes:
            ap = replace(ap, classes=ap.classes + ap.ground_classes)
        by_hue = None
        if ap.hue_classes:
            by_hue = in_roles(surf.classes, ap.hue_classes) & below_camera(local)
        appearance = _colour_check_at_cell_scale(
            image, surf.colour, surf.valid, surf.classes, ap, params, by_hue
        )
    return np.maximum(change, np.float32(params.appearance.weight) * appearance), appearance


def shrink(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``image`` (H, W[, C]) shrunk to ``size`` (width, height) by area: when both sides
    shrink by 2 or more, first by the whole factor ``k`` (k × k blocks averaged: OpenCV's
    fast path, ~4 ms at 12 MP) and then bilinearly by the rest (a factor between 1 and 2),
    where OpenCV's area resize at a fractional factor takes ~60 ms at 12 MP
    (docs/BENCHMARKS.md); otherwise OpenCV's area resize itself."""
    h, w = image.shape[:2]
    k = min(w // size[0], h // size[1])
    if k < 2:
        return np.asarray(cv2.resize(image, size, interpolation=cv2.INTER_AREA))
    blocks = cv2.resize(image, (w // k, h // k), interpolation=cv2.INTER_AREA)
    if blocks.shape[1::-1] == size:
        return np.asarray(blocks)
    return np.asarray(cv2.resize(blocks, size, interpolation=cv2.INTER_LINEAR))


def _cell_shape(shape: tuple[int, ...], params: DetectParams) -> tuple[int, int]:
    """(hs, ws): an image of ``shape`` (H, W, …) scaled so that a superpixel cell is about
    ``CHANGE_CELL_PX`` wide: (H, W) itself up to ~2 MP (1,920 px wide), ~0.48 of it at 12 MP."""
    h, w = shape[:2]
    cell = scale_px(params.graphcut.superpixel_cell_px, w, minimum=2.0)
    scale = min(1.0, CHANGE_CELL_PX / cell)
    return max(1, round(h * scale)), max(1, round(w * scale))


def _sampled(raster: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """``raster`` (H, W, …) at the nearest pixels ``rows`` × ``cols`` (np.take: contiguous,
    without the (hs, W) intermediate of ``raster[rows][:, cols]``)."""
    return np.take(np.take(raster, rows, axis=0), cols, axis=1)


def below_camera(view: View) -> np.ndarray:
    """(H, W) bool: the pixels of ``view`` whose ray points downwards in the local frame (z
    up), i.e. whose points lie below the camera's height, whatever their depth: what a
    street camera looks down on (the pavement, a hedge, a ground floor), not what it looks up
    at (a tree's crown, an upper floor, seen from under them where the scanner saw them from
    the side)."""
    intr = view.intrinsics
    r = np.asarray(view.pose.R, np.float64)  # world → camera; a ray's world z is (Rᵀ d)_z
    r02, r12, r22 = (np.float32(r[i, 2]) for i in range(3))
    if intr.has_distortion:
        rays = camera_rays(intr)  # (H, W, 2): x/z, y/z in the camera frame
        return np.asarray(rays[..., 0] * r02 + rays[..., 1] * r12 + r22 < 0)
    # without distortion x/z depends on the column and y/z on the row alone: no (H, W, 2)
    # raster of rays (at 12 MP it took 0.19 s); the same float32 values as camera_rays'
    x, y = pinhole_axes(intr)
    return np.asarray(x[None, :] * r02 + (y * r12)[:, None] + r22 < 0)


def _colour_check_at_cell_scale(
    image: np.ndarray,
    colour: np.ndarray,
    valid: np.ndarray,
    classes: np.ndarray,
    ap: AppearanceParams,
    params: DetectParams,
    by_hue: np.ndarray | None = None,
) -> np.ndarray:
    """The reference-colour check ``A_p`` (H, W) float32 of ``image`` (H, W, 3) uint8 against
    the old cloud's ``colour`` (H, W, 3) uint8 on the surface ``valid`` (H, W) bool with its
    ``classes`` (H, W) uint8 (and the ``by_hue`` (H, W) bool pixels it checks by hue alone,
    :func:`streetcd.detect.appearance.appearance_change`), computed where a superpixel cell
    is about ``CHANGE_CELL_PX`` wide and upsampled (bilinear), as eq. 5 is
    (:func:`_raw_change_at_cell_scale`): the graph cut sees it through superpixel means, and
    at 12 MP the footprint's hole fill and the colour distances over every pixel took ~0.27 s
    (docs/BENCHMARKS.md). Up to ~2 MP it runs
    at full size, the same to the bit. The image and the surface's rasters are sampled at the
    same pixels (nearest): the check compares the two pixel by pixel, and an image averaged
    by area against reference colours sampled would differ in contrast, which the colour
    transfer then takes for a difference of the cameras."""
    h, w = valid.shape
    hs, ws = _cell_shape((h, w), params)
    if (hs, ws) == (h, w):
        radius = registration_radius_px(w, params.correlate)
        return appearance_change(image, colour, valid, classes, ap, radius, by_hue)
    rows, cols = nearest_index(hs, h), nearest_index(ws, w)
    a = appearance_change(
        _sampled(image, rows, cols),
        _sampled(colour, rows, cols),
        _sampled(valid, rows, cols),
        _sampled(classes, rows, cols),
        ap,
        registration_radius_px(ws, params.correlate),
        None if by_hue is None else _sampled(by_hue, rows, cols),
    )
    return np.asarray(cv2.resize(a, (w, h), interpolation=cv2.INTER_LINEAR), np.float32)


def _neighbour(
    nb_image: np.ndarray,
    nb_surf: ViewSurface,
    nb_local: View,
    surf: ViewSurface,
    local: View,
    view_lut: np.ndarray,
    image: np.ndarray,
    params: DetectParams,
) -> Neighbour:
    """One neighbour ready for eq. 5 (local frame): its colour envelope straight from the
    uint8 image, looked up only where :func:`raw_change` samples it (neither a stretched
    image nor a float envelope is built), through its own stretch or, with
    ``correlate.pair_gain``, through :func:`streetcd.detect.correlate.pair_lut` onto the view's
    (``view_lut``, the view's :func:`~streetcd.detect.correlate.stretch_lut`)."""
    c = params.correlate
    radius = registration_radius_px(nb_local.intrinsics.width, c)
    lo, hi, lut = envelope_levels(nb_image, radius, c.stretch_percentiles)
    fill = 0
    if c.occluder_fill_px > 0:
        fill = round(scale_px(c.occluder_fill_px, nb_local.intrinsics.width))
    holes = hole_depths(nb_surf.depth, fill)
    if c.pair_gain:
        lut = pair_lut(
            image,
            surf.depth,
            local.intrinsics,
            local.pose,
            nb_image,
            nb_surf.depth,
            nb_local.intrinsics,
            nb_local.pose,
            c.stretch_percentiles,
            c.occlusion_tolerance_m,
            lut_p=view_lut,
            lut_q=lut,
            holes_q=holes,
        )
    return Neighbour(
        lo,
        nb_surf.depth,
        nb_local.intrinsics,
        nb_local.pose,
        envelope=(lo, hi),
        lut=lut,
        holes=holes,
    )


def _greys(
    image: np.ndarray, seen: Sequence[NeighbourView]
) -> tuple[np.ndarray, list[NeighbourView]]:
    """The view's and its neighbours' grey levels (uint8, a quarter of float32's memory), the
    neighbours as (grey, depth, intrinsics, pose, holes)."""
    return grey_u8(image), [(grey_u8(i), d, intr, pose, h) for i, d, intr, pose, h in seen]


def _aligned(
    used: Sequence[Neighbour],
    greys: tuple[np.ndarray, Sequence[NeighbourView]],
    surf: ViewSurface,
    local: View,
    params: DetectParams,
) -> tuple[list[Neighbour], WorkingView]:
    """The neighbours of eq. 5 with their registration shifts against the view
    (:mod:`streetcd.detect.align`, measured away from the texture cue's classes), and the view
    and its neighbours at the cue's working size, which the cue reads too."""
    grey, seen = greys
    tp, cp = params.texture, params.correlate
    working = working_view(
        grey, surf.depth, local.intrinsics, local.pose, seen, tp, cp.occlusion_tolerance_m
    )
    where = in_roles(surf.classes, tp.classes) if tp.classes else None
    shifts = neighbour_shifts(
        working, local.intrinsics.width, where, tp, cp.align_shift_px, cp.align_min_gain
    )
    aligned = [replace(nb, offset=shift) for nb, shift in zip(used, shifts, strict=True)]
    return aligned, working


def _texture(
    image: np.ndarray,
    seen: Sequence[NeighbourView],
    surf: ViewSurface,
    local: View,
    params: DetectParams,
    working: WorkingView | None = None,
    coloured: bool = False,
) -> np.ndarray:
    """The texture cue ``T_p`` (:mod:`streetcd.detect.texture`) of the view, on the pixels
    whose old surface is of ``texture.classes`` (all without), and the see-through test over
    railings (:func:`_see_through`) where it is higher, weighted by class like eq. 5. image
    and the neighbours' images: grey levels (:func:`_greys`); working: them at the cue's
    working size (:func:`_aligned`), or None. coloured: the colour check reads the old
    cloud's colours on this view (the see-through test's coarser low-pass then holds,
    ``texture.see_through_colour_blur_px``)."""
    tp = params.texture
    where = None
    if tp.classes:
        where = in_roles(surf.classes, tp.classes)
    texture, _ = texture_change(
        image,
        surf.depth,
        local.intrinsics,
        local.pose,
        seen,
        tp,
        params.correlate.occlusion_tolerance_m,
        scale_px(tp.registration_tolerance_px, local.intrinsics.width, minimum=0.0),
        where,
        tp.blur_px,
        working,
        near_layer(surf.depth, _see_through_roles(surf, tp), tp),
    )
    if tp.see_through_classes:
        see_through = _see_through(image, surf, local, seen, params, coloured)
        np.maximum(texture, see_through, out=texture)
    weigh_low_classes(texture, surf.classes, params.correlate)
    return texture


def _see_through_roles(surf: ViewSurface, tp: TextureParams) -> np.ndarray | None:
    """(H, W) bool, the pixels whose old surface is of ``tp.see_through_classes``, or None
    when there are none."""
    return in_roles(surf.classes, tp.see_through_classes) if tp.see_through_classes else None


def _see_through(
    image: np.ndarray,
    surf: ViewSurface,
    local: View,
    seen: Sequence[NeighbourView],
    params: DetectParams,
    coloured: bool = False,
) -> np.ndarray:
    """The see-through test ``S_p`` (:mod:`streetcd.detect.seethrough`) of the view over the
    footprint of ``texture.see_through_classes``, the appearance check's
    (:func:`streetcd.detect.appearance.footprint`: a railing's bars, gaps and holes); with
    ``coloured`` (the colour check looks at the same footprint), low-passed at least
    ``texture.see_through_colour_blur_px``."""
    tp, ap = params.texture, params.appearance
    close_px = close_width_px(ap, surf.valid.shape[1])
    own = surf.valid & in_roles(surf.classes, tp.see_through_classes)
    inside = footprint(surf.classes, tp.see_through_classes, close_px, ~surf.valid, ap.hole_reach)
    return see_through_change(
        image,
        surf.depth,
        own,
        surf.valid,
        inside,
        local.intrinsics,
        local.pose,
        seen,
        tp,
        params.correlate.occlusion_tolerance_m,
        close_px,
        tp.see_through_colour_blur_px if coloured else 0.0,
    )


def _locating(
    image: np.ndarray,
    surf: ViewSurface,
    local: View,
    seen: Sequence[NeighbourView],
    params: DetectParams,
) -> Working | None:
    """The view and its neighbours at the size where the regions' depths are measured
    (:func:`streetcd.detect.locate.working_set`); None without a neighbour. Its callers ask
    only when ``locate.enabled`` and the view has regions."""
    lp = params.locate
    return working_set(
        image,
        surf.depth,
        local.intrinsics,
        seen,
        window_px=lp.window_px,
        scale=lp.scale,
        max_work_px=lp.max_work_width_px,
        percentiles=params.correlate.stretch_percentiles,
    )


def _located(
    regions: list[Region],
    region_labels: np.ndarray,
    working: Working,
    local: View,
    params: DetectParams,
) -> list[Region]:
    """The regions with their depth fractions (:mod:`streetcd.detect.locate`)."""
    lp = params.locate
    fractions = region_depth_fractions(
        working,
        region_labels,
        len(regions),
        local.pose,
        fractions=lp.fractions(),
        min_gain=lp.min_gain,
        min_pixels=lp.min_pixels,
        max_samples=lp.max_samples,
        occlusion_tolerance_m=params.correlate.occlusion_tolerance_m,
    )
    return [replace(r, depth_fraction=float(f)) for r, f in zip(regions, fractions, strict=True)]


def _nearer(
    image: np.ndarray,
    surf: ViewSurface,
    local: View,
    seen: Sequence[NeighbourView],
    params: DetectParams,
) -> np.ndarray:
    """The nearer-depth test ``N_p`` (:mod:`streetcd.detect.sweep`), weighted by class like
    eq. 5."""
    cp = params.correlate
    nearer = nearer_depth_change(
        image,
        surf.depth,
        local.intrinsics,
        local.pose,
        seen,
        fractions=cp.nearer_fractions,
        margin=cp.nearer_margin,
        span=cp.nearer_span,
        match=cp.nearer_match,
        window_px=cp.nearer_window_px,
        scale=cp.nearer_scale,
        max_work_px=params.texture.max_work_width_px,
        occlusion_tolerance_m=cp.occlusion_tolerance_m,
        percentiles=cp.stretch_percentiles,
    )
    weigh_low_classes(nearer, surf.classes, cp)
    return nearer


# What a cache is told once its cloud's classes have been checked (streetcd run's workers
# are told before their first view: the night's input check has said it, once).
CLASSES_CHECKED = "classes checked"


def _check_classes(cloud: PointCloud, params: DetectParams, cache: SurfaceCache | None) -> None:
    """Warn when the cloud's classes are of no use to the detector (its codes are not in the
    class map, or it is unclassified), or when most of its points are in no role: once per
    cache (a worker's run), or at every call without one."""
    if cache is not None and not cache.first_time(CLASSES_CHECKED):
        return
    why = useless_classes(cloud.classification, params.classes)
    if why is None:  # useful classes, but on a minority of the points
        why = mostly_roleless(cloud.classification, params.classes)
    if why is not None:
        log.warning(why)


def reference_kind(
    cloud: PointCloud, params: DetectParams, cache: SurfaceCache | None = None
) -> str | None:
    """What the surfaces' ``colour`` raster holds for ``cloud``: "colour" (the cloud's own,
    for the reference-colour check), "intensity" (its intensity codes, for the intensity
    check, when it has no colours), or None (the check is off, or the cloud has neither)."""
    if not params.appearance.enabled:
        return None
    if _rgb8_of(cloud, params, cache) is not None:
        return "colour"
    if params.appearance.intensity and intensity_codes(cloud.intensity) is not None:
        return "intensity"
    return None


def _rgb8_of(
    cloud: PointCloud, params: DetectParams, cache: SurfaceCache | None
) -> np.ndarray | None:
    """The cloud's 8-bit colours when the appearance check wants them, else None."""
    if not wants_colour(cloud, params) or cloud.rgb is None:
        return None
    return cache.cloud_rgb8(cloud) if cache is not None else cloud_rgb8(cloud.rgb)


def _tell_no_colours(cache: SurfaceCache | None, kind: str | None = None) -> None:
    """Warn that the appearance check is off for want of colours (or, ``kind`` "intensity",
    that the intensity check stands in for it): once per cache (a worker's run), or at every
    call without one."""
    if kind == "intensity":
        if cache is None or cache.first_time("intensity instead of colours"):
            log.info(
                "the reference cloud has no colours: the intensity check "
                "(streetcd.detect.intensity) stands in for the reference-colour check"
            )
        return
    if cache is None or cache.first_time("no colours"):
        log.warning(
            "the reference cloud has no colours (none, or all zero): the reference-colour check "
            "(streetcd.detect.appearance) is off and removed or replaced objects in front of "
            "plain backgrounds will be missed (the paper's method alone)"
        )


def gate_second_smallest(
    change: np.ndarray,
    minimum: np.ndarray,
    image: np.ndarray,
    surf: ViewSurface,
    local: View,
    params: DetectParams,
) -> np.ndarray:
    """``change`` (H, W) float32, eq. 5's second-smallest difference, with eq. 5's
    ``minimum`` (H, W) float32 put back wherever the view ``image`` (H, W, 3) uint8 shows the
    old cloud's colour (``surf.colour``, moved onto the image by the reference-colour check's
    transfer) within the registration radius: the distance of
    :func:`streetcd.detect.appearance.reference_distance` below
    ``params.correlate.second_smallest_gate``. There the old surface is what the view shows,
    and neighbours that disagree see something new standing in front of it. Only the pixels
    where the two differ are looked at."""
    differ = change > minimum
    if not differ.any() or surf.colour is None:
        return change
    radius = registration_radius_px(local.intrinsics.width, params.correlate)
    square = np.ones((2 * radius + 1, 2 * radius + 1), np.uint8)
    near = (cv2.dilate(differ.astype(np.uint8), square) > 0) & surf.valid if radius else differ
    ap = params.appearance
    luts = transfer_luts(surf.colour, image, surf.valid, ap.transfer)
    distance = reference_distance(image[near], surf.colour[near], luts, ap)
    same = np.zeros(differ.shape, np.uint8)
    same[near] = distance < params.correlate.second_smallest_gate
    held = cv2.dilate(same, square) if radius else same  # within the registration radius
    keep = differ & (held > 0) & surf.valid
    return np.where(keep, minimum, change).astype(np.float32)


def _raw_change_at_cell_scale(
    stretched: np.ndarray,
    depth: np.ndarray,
    classes: np.ndarray,
    local: View,
    used: Sequence[Neighbour],
    params: DetectParams,
    keep_minimum: bool = False,
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Raw change (eq. 5) of the view's (H, W) ``depth`` and ``classes`` rasters (its
    surface, or a second depth hypothesis), computed at a resolution where a superpixel cell
    is about ``CHANGE_CELL_PX`` wide and upsampled (bilinear); with ``keep_minimum`` (and
    ``correlate.second_smallest``), eq. 5's minimum beside it, else None.

    The graph cut only sees the raw change averaged over superpixels, so sampling it 4 times
    more coarsely on a 12 MP view changes little and saves most of its cost (docs/BENCHMARKS.md); a 2 MP view
    (24 px cells) is computed at full resolution. Depth and classes are resampled nearest,
    so no depth is blended across an occlusion edge.
    """
    h, w = depth.shape
    hs, ws = _cell_shape((h, w), params)
    intr = local.intrinsics
    keep = keep_minimum and params.correlate.second_smallest
    minimum = np.empty((hs, ws), np.float32) if keep else None
    if (hs, ws) == (h, w):
        change, support = raw_change(
            stretched, depth, classes, intr, local.pose, used, params.correlate, minimum
        )
        return change, support, minimum
    sx, sy = ws / w, hs / h
    small = Intrinsics(
        ws,
        hs,
        intr.fx * sx,
        intr.fy * sy,
        (intr.cx + 0.5) * sx - 0.5,
        (intr.cy + 0.5) * sy - 0.5,
        intr.dist,
    )
    rows, cols = nearest_index(hs, h), nearest_index(ws, w)
    used = [replace(nb, offset=(nb.offset[0] * sy, nb.offset[1] * sx)) for nb in used]
    change, support = raw_change(
        shrink(stretched, (ws, hs)),
        _sampled(depth, rows, cols),
        _sampled(classes, rows, cols),
        small,
        local.pose,
        used,
        params.correlate,
        minimum,
    )
    return (
        cv2.resize(change, (w, h), interpolation=cv2.INTER_LINEAR),
        cv2.resize(support, (w, h), interpolation=cv2.INTER_NEAREST),
        None if minimum is None else cv2.resize(minimum, (w, h), interpolation=cv2.INTER_LINEAR),
    )


def _outline_grey(
    image: np.ndarray, view_lut: np.ndarray, params: DetectParams
) -> np.ndarray | None:
    """(H, W) uint8 grey levels of the stretched view, where the near-depth band's outline is
    looked for (None when ``correlate.silhouette_edge_threshold`` is 0): the uint8 table on
    the uint8 image gives what truncating the stretched float image would, at a fraction of
    its cost."""
    if params.correlate.silhouette_edge_threshold <= 0:
        return None
    return grey_u8(cv2.LUT(np.ascontiguousarray(image), view_lut.astype(np.uint8)))


def _with_near_hypothesis(
    change: np.ndarray,
    stretched: np.ndarray,
    surf: ViewSurface,
    local: View,
    used: Sequence[Neighbour],
    params: DetectParams,
    grey: np.ndarray | None,
) -> np.ndarray:
    """``change`` (H, W) float32 under the near-depth hypothesis of :mod:`streetcd.detect.silhouette`:
    where the hypothesis exists, the smaller of the two raw changes when a neighbour sees the
    nearer point, else 0 (no neighbour can tell the two apart). ``grey`` (H, W) uint8, the
    view's levels from :func:`_outline_grey`: a near object's band keeps within its outline
    there (None: every band is its reach). Updates ``change`` in place and returns it."""
    # the ground's and the road's bands are their reach (they have no unscanned side)
    bounded = None if grey is None else ~in_roles(surf.classes, GROUND_ROLES)
    near = near_depth_hypothesis(
        surf.depth,
        local.intrinsics.fx,
        params.correlate.silhouette_margin_m,
        params.surface.max_depth_jump_m,
        grey=grey,
        edge_threshold=params.correlate.silhouette_edge_threshold,
        bounded=bounded,
    )
    if not np.isfinite(near).any():
        return change
    near_change, near_support, _ = _raw_change_at_cell_scale(
        stretched, near, surf.classes, local, used, params
    )
    # a pixel that may be the unscanned side of a near object and that no neighbour can
    # check at that depth gives no evidence, as a pixel that no neighbour sees (eq. 5);
    # in place: at 12 MP each full-size temporary is 48 MB
    checked = near_support > 0
    np.minimum(change, near_change, out=change, where=checked)
    change[~checked & np.isfinite(near)] = 0.0
    return change
