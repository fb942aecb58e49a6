"""One view end to end (paper §3.2–3.4): the only module that chains the steps.

:func:`detect_view` is the pure kernel (arrays in, :class:`DetectionResult` out):

1. surface of the view and of each neighbour from the reference cloud (z-buffer eq. 1–3,
   view-dependent triangulation; :func:`streetcd.surface.surface_for_view`);
2. histogram stretching of every image and the raw change ``C_p`` (eq. 4–5,
   :mod:`streetcd.correlate`), fused with the reference-colour check ``A_p`` (not in the
   paper; :mod:`streetcd.appearance`) as ``max(C_p, k · A_p)``;
3. node energy (eq. 7), class-aware superpixels (eq. 10–11), graph cut (eq. 6, 8–9) and
   speckle filter (:mod:`streetcd.graphcut`);
4. each changed region's outline redrawn at pixel level by colour, within half a superpixel
   of the cut's (not in the paper; :mod:`streetcd.refine`), and the speckle filter again;
5. the changed regions: 8-connected components of the mask, each with a score (mean node
   energy), its 3D centroid and extent from the depth raster and the dominant class.

Below it, file-level helpers for the CLI and the flows: :func:`read_image`,
:func:`load_clouds`, :func:`detect_files` and :func:`write_outputs`.

Note on regions: the depth raster is the *old* surface. For an added object the region's 3D
position is the surface behind it (the wall, the ground), for a removed one the object
itself; either way it locates the change on the street to within the object's depth.
"""

from __future__ import annotations

import json
import logging
import math
import time
import weakref
import zlib
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from streetcd.appearance import appearance_change
from streetcd.camera import Intrinsics, backproject
from streetcd.correlate import (
    Neighbour,
    envelope_levels,
    hole_depths,
    pair_lut,
    raw_change,
    registration_radius_px,
    stretch_lut,
)
from streetcd.errors import (
    CorruptFileError,
    CRSMismatchError,
    EmptyViewError,
    InputError,
    MissingInputError,
)
from streetcd.graphcut import cut_changes, nearest_index, node_energy
from streetcd.io.las import PointCloud
from streetcd.memo import ArrayMemo
from streetcd.params import DetectParams, scale_px
from streetcd.refine import refined_mask
from streetcd.views import PoseSet, View

_DEFAULTS = DetectParams()  # frozen: one shared default instance
log = logging.getLogger(__name__)
_told_no_colours = False  # said once per process: every view of such a cloud is the same

BBOX_PERCENTILES = (2.0, 98.0)  # region extent: drop the few edge pixels that hit background
CHANGE_CELL_PX = 24.0  # raw change runs where a superpixel cell is about this wide
_REGION_SAMPLES = 20_000  # pixels back-projected per region (evenly spread) for its 3D extent


@dataclass(frozen=True)
class Region:
    """One changed region (an 8-connected component of the mask).

    label : id in :attr:`DetectionResult.region_labels` (1, 2, …).
    pixels : number of pixels. score : mean node energy over them, in [0, 1].
    centroid, bbox_min, bbox_max : (3,) float64 metres, local frame (add ``origin`` for the
    CRS); mean and 2nd/98th percentiles of the region's pixels (up to 20 000, evenly
    spread) back-projected through the depth raster; NaN when none has a surface.
    dominant_class : most frequent class code of the old cloud under the region (0 = none).
    """

    label: int
    pixels: int
    score: float
    centroid: np.ndarray
    bbox_min: np.ndarray
    bbox_max: np.ndarray
    dominant_class: int


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
    ``appearance`` (H, W) float32 ``A_p`` of :mod:`streetcd.appearance` in [0, 1], or None
    when the check is off or the cloud has no colours. The node energy is eq. 7 of
    ``max(raw_change, weight · appearance)``. ``cut_mask`` (H, W) bool is the superpixel
    cut's mask before :mod:`streetcd.refine` redrew its outlines (``mask`` when that is off).
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


def _check_image(image: np.ndarray, view: View) -> np.ndarray:
    image = np.asarray(image)
    intr = view.intrinsics
    if image.dtype != np.uint8 or image.shape != (intr.height, intr.width, 3):
        raise InputError(
            f"view {view.name!r}: image is {image.dtype} {image.shape}, the "
            f"camera expects uint8 ({intr.height}, {intr.width}, 3)"
        )
    return image


class SurfaceCache:
    """A small LRU of view surfaces (:func:`streetcd.surface.surface_for_view`), bounded by
    bytes, so that detecting a segment's views in order builds each surface once instead of
    up to 1 + n_neighbours times (a view is the neighbour of the views around it).

    A surface depends on the cloud, the view's camera and pose, its image (the colours of
    eq. 2) and the z-buffer, surface and range parameters. The key holds the view's name,
    pose, intrinsics, a CRC-32 of the image bytes (:func:`image_checksum`: once per
    read-only image), those parameters and the cloud's identity: ``id`` of its xyz and
    classification arrays, their length and the origin. A hit also checks, through weak references, that those very
    arrays are still alive (an ``id`` can be reused after one is freed). Not detected:
    a cloud array changed *in place* after a surface was built from it; call
    :meth:`clear` after doing that. A cloud cropped anew per view (as
    :func:`streetcd.crop.crop_for_view` does) is a new cloud: no hit, by design, since its
    points differ; surfaces of clouds that have been freed are dropped at the next lookup, so
    such a flow holds no more than the current view's surfaces.
    """

    def __init__(self, max_bytes: int = 448 * 2**20) -> None:
        # default: a 12 MP view and its 3 neighbours (108 MB each with the cloud's colours).
        # At 320 MiB only 3 fitted, and detecting one view evicted each surface just before
        # it was needed again (7 builds, 0 hits, per view).
        self.max_bytes = int(max_bytes)
        self._entries: OrderedDict[tuple, tuple[Any, Any, Any]] = OrderedDict()
        self._bytes = 0
        self.hits = 0
        self.misses = 0

    @staticmethod
    def key(image: np.ndarray, local: View, cloud: PointCloud, params: DetectParams) -> tuple:
        intr, pose = local.intrinsics, local.pose
        return (
            local.name,
            pose.R.tobytes(),
            pose.t.tobytes(),
            intr,
            image.shape,
            image_checksum(image),
            params.zbuffer,
            params.surface,
            params.max_range_m,
            _wants_colour(cloud, params),
            id(cloud.rgb),
            id(cloud.xyz),
            id(cloud.classification),
            len(cloud.xyz),
            np.asarray(cloud.origin, np.float64).tobytes(),
        )

    def get(self, key: tuple, cloud: PointCloud) -> Any:
        self._drop_dead()
        entry = self._entries.get(key)
        if entry is None or entry[1]() is not cloud.xyz or entry[2]() is not cloud.classification:
            self.misses += 1
            return None
        self._entries.move_to_end(key)
        self.hits += 1
        return entry[0]

    def put(self, key: tuple, cloud: PointCloud, surf: Any) -> None:
        size = _surface_bytes(surf)
        if size > self.max_bytes:
            return
        for array in (surf.depth, surf.classes, surf.valid, surf.colour):
            if array is not None:
                array.flags.writeable = False  # shared by every result that reuses it
        self._drop_dead()
        old = self._entries.pop(key, None)
        if old is not None:
            self._bytes -= _surface_bytes(old[0])
        self._entries[key] = (surf, weakref.ref(cloud.xyz), weakref.ref(cloud.classification))
        self._bytes += size
        while self._bytes > self.max_bytes:
            _, (dropped, _, _) = self._entries.popitem(last=False)
            self._bytes -= _surface_bytes(dropped)

    def _drop_dead(self) -> None:
        """Forget surfaces of clouds that no longer exist: they can never hit again (a
        flow that crops a new cloud per view leaves only those behind)."""
        dead = [k for k, (_, xyz, cls) in self._entries.items() if xyz() is None or cls() is None]
        for k in dead:
            self._bytes -= _surface_bytes(self._entries.pop(k)[0])

    def clear(self) -> None:
        self._entries.clear()
        self._bytes = 0

    def __len__(self) -> int:
        return len(self._entries)


_CHECKSUMS = ArrayMemo()  # a read-only image → its CRC-32


def image_checksum(image: np.ndarray) -> int:
    """CRC-32 of the image's bytes (~3 ms at 2 MP, 13 ms at 12 MP, mostly reading them).

    For a read-only array that owns its data, which nothing can change, the CRC is kept
    while the array lives: a view and the three views it neighbours then checksum their
    shared image once, not four times (the flow's image cache hands out such arrays,
    :func:`streetcd.pipeline.read_rgb`).
    """
    if not image.flags.writeable and image.flags.owndata:
        return int(_CHECKSUMS.get(image, _crc32))
    return _crc32(image)


def _crc32(image: np.ndarray) -> int:
    return zlib.crc32(np.ascontiguousarray(image).data.cast("B"))


def _surface_bytes(surf: Any) -> int:
    colour = 0 if surf.colour is None else surf.colour.nbytes
    return surf.depth.nbytes + surf.classes.nbytes + surf.valid.nbytes + colour


def _wants_colour(cloud: PointCloud, params: DetectParams) -> bool:
    """Whether surfaces carry the reference colours: the appearance check is on and the
    cloud has colours."""
    return params.appearance.enabled and cloud.rgb is not None


SURFACES = SurfaceCache()  # per process: a worker detecting a segment's views reuses them

# the last cloud colour array seen and its 8-bit version (None: all zero)
_last_rgb8: tuple[weakref.ref, np.ndarray | None] | None = None


def _cloud_rgb8(cloud: PointCloud) -> np.ndarray | None:
    """The cloud's colours as (N, 3) uint8 (:func:`streetcd.surface.rgb8`), None when it has
    none or all are zero.

    Kept for the last colour array seen (a weak reference: it goes with the cloud), so
    that a view and its neighbours convert the cloud once, not once per surface (two
    passes over every point, ~5 ms per 3 M points). As with :class:`SurfaceCache`, a
    colour array changed *in place* is not noticed.
    """
    global _last_rgb8
    from streetcd.surface import rgb8

    if cloud.rgb is None:
        return None
    if _last_rgb8 is not None and _last_rgb8[0]() is cloud.rgb:
        return _last_rgb8[1]
    rgb: np.ndarray | None = rgb8(cloud.rgb)
    if rgb is not None and not rgb.any():
        # LAS formats 2, 3, 5, 7, 8 and 10 always have RGB fields; all zero means the
        # writer had no colours, not a black street
        rgb = None
    _last_rgb8 = (weakref.ref(cloud.rgb), rgb)
    return rgb


def _surface(
    image: np.ndarray,
    local: View,
    cloud: PointCloud,
    params: DetectParams,
    cache: SurfaceCache | None,
) -> Any:
    """The view's surface from ``cache`` or built (and cached); EmptyViewError as
    :func:`streetcd.surface.surface_for_view`."""
    from streetcd.surface import surface_for_view

    def build() -> Any:
        rgb = _cloud_rgb8(cloud) if _wants_colour(cloud, params) else None
        return surface_for_view(
            cloud.xyz, cloud.classification, image, local.intrinsics, local.pose, params, rgb
        )[0]

    if cache is None:
        return build()
    key = cache.key(image, local, cloud, params)
    surf = cache.get(key, cloud)
    if surf is None:
        surf = build()
        cache.put(key, cloud, surf)
    return surf


def detect_view(
    image: np.ndarray,
    view: View,
    neighbours: Sequence[tuple[np.ndarray, View]],
    cloud: PointCloud,
    params: DetectParams = _DEFAULTS,
    *,
    surfaces: SurfaceCache | None = SURFACES,
) -> DetectionResult:
    """Change mask of one view against the reference cloud (paper §3.2–3.4).

    image : (H, W, 3) uint8 RGB of ``view``. neighbours : (image, view) pairs of overlapping
    views (the paper uses 2–3). Views carry CRS poses; they are moved into the cloud's local
    frame (``view.local(cloud.origin)``). A neighbour that sees no point is left out.
    surfaces : where surfaces are looked up and kept (:class:`SurfaceCache`; the process-wide
    ``SURFACES`` by default, None to build every surface afresh). The result is the same
    either way; the surfaces in it are shared with the cache and must not be modified.

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
    try:
        surf = _surface(image, local, cloud, params, surfaces)
    except EmptyViewError as exc:
        raise EmptyViewError(f"view {view.name!r} sees no reference points: {exc}") from None
    if not surf.valid.any():
        raise EmptyViewError(
            f"view {view.name!r} sees no reference surface (points project but form no triangle)"
        )
    lap("surface")
    used: list[Neighbour] = []
    names: list[str] = []
    view_lut = stretch_lut(image, params.correlate.stretch_percentiles)
    for nb_image, nb_view in neighbours:
        nb_image = _check_image(nb_image, nb_view)
        nb_local = nb_view.local(cloud.origin)
        try:
            nb_surf = _surface(nb_image, nb_local, cloud, params, surfaces)
        except EmptyViewError:
            lap("surface")
            continue  # a neighbour without points gives no evidence
        lap("surface")
        used.append(_neighbour(nb_image, nb_surf, nb_local, surf, local, view_lut, image, params))
        names.append(nb_view.name)
        lap("stretch")
    stretched = cv2.LUT(np.ascontiguousarray(image), view_lut)  # = stretch_histogram(image)
    lap("stretch")
    change, support = _raw_change_at_cell_scale(
        stretched, surf.depth, surf.classes, local, used, params
    )
    if params.correlate.silhouette_margin_m > 0 and used:
        change = _with_near_hypothesis(change, stretched, surf, local, used, params)
    used.clear()  # their envelopes and depths (360 MB at 12 MP) are not needed past eq. 5
    lap("raw_change")
    if params.appearance.enabled and surf.colour is None:
        _tell_no_colours()
    fused, appearance = fuse_appearance(image, surf, change, local, params)
    if appearance is not None:
        lap("appearance")
    energy = node_energy(fused, params.graphcut.a, params.graphcut.b)
    lap("node_energy")
    cut = cut_changes(energy, stretched, surf.depth, surf.classes, params.graphcut)
    lap("graphcut")
    mask = refined_mask(image, cut.mask, params)
    lap("refine")
    region_labels, regions = changed_regions(
        mask, energy, surf.depth, surf.classes, local.intrinsics, local.pose
    )
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
    )


def fuse_appearance(
    image: np.ndarray, surf: Any, change: np.ndarray, local: View, params: DetectParams
) -> tuple[np.ndarray, np.ndarray | None]:
    """The change eq. 7 sees, ``max(C_p, k · A_p)``, and ``A_p`` (:mod:`streetcd.appearance`)
    of the view ``image`` (H, W, 3) uint8 on its surface ``surf``; ``(change, None)`` when the
    check is off or the surface has no colours. change : (H, W) float32 raw change."""
    if not params.appearance.enabled or surf.colour is None:
        return change, None
    appearance = appearance_change(
        image,
        surf.colour,
        surf.valid,
        surf.classes,
        params.appearance,
        registration_radius_px(local.intrinsics.width, params.correlate),
    )
    return np.maximum(change, np.float32(params.appearance.weight) * appearance), appearance


def _neighbour(
    nb_image: np.ndarray,
    nb_surf: Any,
    nb_local: View,
    surf: Any,
    local: View,
    view_lut: np.ndarray,
    image: np.ndarray,
    params: DetectParams,
) -> Neighbour:
    """One neighbour ready for eq. 5 (local frame): its colour envelope straight from the
    uint8 image, looked up only where :func:`raw_change` samples it (neither a stretched
    image nor a float envelope is built), through its own stretch or, with
    ``correlate.pair_gain``, through :func:`streetcd.correlate.pair_lut` onto the view's
    (``view_lut``, the view's :func:`~streetcd.correlate.stretch_lut`)."""
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


def _tell_no_colours() -> None:
    global _told_no_colours
    if not _told_no_colours:
        _told_no_colours = True
        log.warning(
            "the reference cloud has no colours (none, or all zero): the reference-colour check "
            "(streetcd.appearance) is off and removed or replaced objects in front of "
            "plain backgrounds will be missed (the paper's method alone)"
        )


def _raw_change_at_cell_scale(
    stretched: np.ndarray,
    depth: np.ndarray,
    classes: np.ndarray,
    local: View,
    used: Sequence[Neighbour],
    params: DetectParams,
) -> tuple[np.ndarray, np.ndarray]:
    """Raw change (eq. 5) of the view's (H, W) ``depth`` and ``classes`` rasters (its
    surface, or a second depth hypothesis), computed at a resolution where a superpixel cell
    is about ``CHANGE_CELL_PX`` wide and upsampled (bilinear).

    The graph cut only sees the raw change averaged over superpixels, so sampling it 4 times
    more coarsely on a 12 MP view changes little and saves ~3/4 of its cost; a 2 MP view
    (24 px cells) is computed at full resolution. Depth and classes are resampled nearest,
    so no depth is blended across an occlusion edge.
    """
    h, w = depth.shape
    cell = scale_px(params.graphcut.superpixel_cell_px, w, minimum=2.0)
    scale = min(1.0, CHANGE_CELL_PX / cell)
    intr = local.intrinsics
    hs, ws = max(1, round(h * scale)), max(1, round(w * scale))
    if (hs, ws) == (h, w):
        return raw_change(stretched, depth, classes, intr, local.pose, used, params.correlate)
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
    change, support = raw_change(
        cv2.resize(stretched, (ws, hs), interpolation=cv2.INTER_AREA),
        # np.take: contiguous, without the (hs, W) intermediate of a[rows][:, cols]
        np.take(np.take(depth, rows, axis=0), cols, axis=1),
        np.take(np.take(classes, rows, axis=0), cols, axis=1),
        small,
        local.pose,
        used,
        params.correlate,
    )
    return (
        cv2.resize(change, (w, h), interpolation=cv2.INTER_LINEAR),
        cv2.resize(support, (w, h), interpolation=cv2.INTER_NEAREST),
    )


def _with_near_hypothesis(
    change: np.ndarray,
    stretched: np.ndarray,
    surf: Any,
    local: View,
    used: Sequence[Neighbour],
    params: DetectParams,
) -> np.ndarray:
    """``change`` (H, W) float32 under the near-depth hypothesis of :mod:`streetcd.silhouette`:
    where the hypothesis exists, the smaller of the two raw changes when a neighbour sees the
    nearer point, else 0 (no neighbour can tell the two apart). Updates ``change`` in place
    and returns it."""
    from streetcd.silhouette import near_depth_hypothesis

    near = near_depth_hypothesis(
        surf.depth,
        local.intrinsics.fx,
        params.correlate.silhouette_margin_m,
        params.surface.max_depth_jump_m,
    )
    if not np.isfinite(near).any():
        return change
    near_change, near_support = _raw_change_at_cell_scale(
        stretched, near, surf.classes, local, used, params
    )
    # a pixel that may be the unscanned side of a near object and that no neighbour can
    # check at that depth gives no evidence, as a pixel that no neighbour sees (eq. 5);
    # in place: at 12 MP each full-size temporary is 48 MB
    checked = near_support > 0
    np.minimum(change, near_change, out=change, where=checked)
    change[~checked & np.isfinite(near)] = 0.0
    return change


def changed_regions(
    mask: np.ndarray,
    energy: np.ndarray,
    depth: np.ndarray,
    classes: np.ndarray,
    intrinsics: Intrinsics,
    pose: Any,
) -> tuple[np.ndarray, list[Region]]:
    """8-connected components of ``mask`` (H, W) bool as :class:`Region` s.

    energy (H, W) float32 node energy, depth (H, W) float32 metres, classes (H, W) uint8,
    pose in the local frame. Returns the (H, W) int32 label image (0 = none) and the regions.
    """
    from scipy import ndimage

    if not mask.any():  # most views: skip labelling and scanning a blank image
        return np.zeros(mask.shape, np.int32), []
    n, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8, ltype=cv2.CV_32S)
    regions: list[Region] = []
    for k, box in enumerate(ndimage.find_objects(labels), start=1):
        if box is None:
            continue
        rows, cols = np.nonzero(labels[box] == k)
        rows, cols = rows + box[0].start, cols + box[1].start
        z = depth[rows, cols]
        has = np.isfinite(z)
        if has.any():
            pick = np.flatnonzero(has)[:: max(1, int(has.sum()) // _REGION_SAMPLES)]
            pts = backproject(
                np.column_stack([cols[pick], rows[pick]]).astype(np.float64),
                z[pick].astype(np.float64),
                intrinsics,
                pose,
            )
            centroid = pts.mean(axis=0)
            lo, hi = np.percentile(pts, BBOX_PERCENTILES, axis=0)
            dominant = int(np.bincount(classes[rows[has], cols[has]], minlength=256).argmax())
        else:
            centroid = lo = hi = np.full(3, np.nan)
            dominant = 0
        regions.append(
            Region(
                label=k,
                pixels=int(rows.size),
                score=float(energy[rows, cols].mean()),
                centroid=centroid,
                bbox_min=lo,
                bbox_max=hi,
                dominant_class=dominant,
            )
        )
    return labels, regions


# --- file-level helpers (CLI, flows) -------------------------------------------------------


def read_image(path: str | Path) -> np.ndarray:
    """Read an image file as (H, W, 3) uint8 RGB.

    MissingInputError if it does not exist, CorruptFileError naming the file if it cannot be
    decoded or a JPEG is truncated (libjpeg would return the top half and a grey rest).
    """
    path = Path(path)
    if not path.is_file():
        raise MissingInputError(f"image not found: {path}")
    return decode_rgb(path, np.fromfile(path, dtype=np.uint8))


def decode_rgb(path: Path, data: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB image from the bytes ``data`` of the file ``path``;
    CorruptFileError naming the file if they cannot be decoded or a JPEG is truncated
    (libjpeg would return the top half and a grey rest; OpenCV 5 refuses it, earlier
    releases did not)."""
    if path.suffix.lower() in (".jpg", ".jpeg") and b"\xff\xd9" not in data[-64:].tobytes():
        raise CorruptFileError(f"{path}: truncated JPEG (no end-of-image marker)")
    # decoded straight to RGB: the same pixels as BGR then cvtColor, without the copy
    rgb = cv2.imdecode(data, cv2.IMREAD_COLOR_RGB) if data.size else None
    if rgb is None:
        raise CorruptFileError(f"{path}: cannot be decoded as an image ({data.size} bytes)")
    return rgb


def load_clouds(paths: Sequence[str | Path]) -> PointCloud:
    """Read several LAS/LAZ files into one cloud in one local frame (the first file's offset).

    Files have different header offsets, so every file is read relative to the same origin.
    CRSMismatchError if two files state different CRSs.
    """
    from streetcd.io.las import read_las

    if not paths:
        raise MissingInputError("no point cloud file given")
    first = read_las(paths[0])
    clouds = [first] + [read_las(p, origin=first.origin) for p in paths[1:]]
    crss = {c.crs for c in clouds if c.crs is not None}
    if len(crss) > 1:
        listed = ", ".join(f"{p}: {c.crs}" for p, c in zip(paths, clouds, strict=True))
        raise CRSMismatchError(f"point cloud files have different CRSs ({listed})")
    return PointCloud(
        xyz=np.concatenate([c.xyz for c in clouds]),
        origin=first.origin,
        classification=np.concatenate([c.classification for c in clouds]),
        # colours only when every file has them (the appearance check needs all or none)
        rgb=(
            np.concatenate([c.rgb for c in clouds])
            if all(c.rgb is not None for c in clouds)
            else None
        ),
        crs=next(iter(crss), None),
    )


def detect_files(
    view_name: str,
    poses: PoseSet,
    image_dir: str | Path,
    cloud: PointCloud,
    params: DetectParams = _DEFAULTS,
    neighbour_names: Sequence[str] | None = None,
) -> tuple[DetectionResult, View, np.ndarray]:
    """Detect changes in the view ``view_name`` of ``poses`` with images from ``image_dir``.

    Without ``neighbour_names`` the overlapping views are chosen by
    :func:`streetcd.neighbours.select_neighbours`. Returns the result, the view and its
    image. Errors name the view and the cause (missing pose, unreadable image, no points).
    """
    from streetcd.neighbours import select_neighbours

    view = poses.get(view_name)
    if poses.crs and cloud.crs and poses.crs != cloud.crs:
        raise CRSMismatchError(f"poses {poses.source} are in {poses.crs}, the cloud in {cloud.crs}")
    if neighbour_names is None:
        nb_views = select_neighbours(view, poses.views, n=params.correlate.n_neighbours)
    else:
        nb_views = [poses.get(n) for n in neighbour_names]

    def image_of(v: View) -> np.ndarray:
        try:
            return read_image(Path(image_dir) / v.name)
        except (CorruptFileError, MissingInputError) as exc:
            raise type(exc)(f"view {v.name!r}: {exc}") from None

    image = image_of(view)
    neighbours = [(image_of(v), v) for v in nb_views]
    return detect_view(image, view, neighbours, cloud, params), view, image


def _atomic_write(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(data)
    tmp.replace(path)


def _encode(ext: str, array: np.ndarray) -> bytes:
    ok, buf = cv2.imencode(ext, array)
    if not ok:
        raise InputError(f"cannot encode a {array.shape} array as {ext}")
    return buf.tobytes()


def overlay(image: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 RGB: ``image`` with the changed pixels tinted red and outlined."""
    out = image.copy()
    out[mask] = (0.5 * out[mask] + np.array([127.5, 0.0, 0.0])).astype(np.uint8)
    contours, _ = cv2.findContours(
        mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE
    )
    cv2.drawContours(out, contours, -1, (255, 255, 0), max(1, image.shape[1] // 800))
    return out


def summary(result: DetectionResult, view: View) -> dict[str, Any]:
    """The JSON summary of one view: score, changed fraction, regions in CRS metres, timings."""

    def crs(local: np.ndarray) -> list[float | None]:
        return [
            None if not math.isfinite(v) else round(float(v), 3)
            for v in np.asarray(local) + result.origin
        ]

    return {
        "view": view.name,
        "score": round(result.score, 4),
        "changed_fraction": round(result.changed_fraction, 6),
        "neighbours": list(result.neighbours),
        # False when the cloud has no colours or the check is switched off
        "appearance_check": result.appearance is not None,
        "origin": [float(v) for v in result.origin],
        "regions": [
            {
                "label": r.label,
                "pixels": r.pixels,
                "score": round(r.score, 4),
                "centroid": crs(r.centroid),
                "bbox_min": crs(r.bbox_min),
                "bbox_max": crs(r.bbox_max),
                "dominant_class": r.dominant_class,
            }
            for r in result.regions
        ],
        "timings_s": {k: round(v, 4) for k, v in result.timings.items()},
    }


def write_outputs(
    result: DetectionResult, view: View, image: np.ndarray, out_dir: str | Path
) -> dict[str, Path]:
    """Write ``<stem>.mask.png`` (uint8 0/255), ``<stem>.overlay.jpg`` and ``<stem>.json``
    into ``out_dir``, each atomically. Returns the paths by kind."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {
        "mask": out / f"{view.stem}.mask.png",
        "overlay": out / f"{view.stem}.overlay.jpg",
        "summary": out / f"{view.stem}.json",
    }
    _atomic_write(paths["mask"], _encode(".png", result.mask.astype(np.uint8) * 255))
    bgr = cv2.cvtColor(overlay(image, result.mask), cv2.COLOR_RGB2BGR)
    _atomic_write(paths["overlay"], _encode(".jpg", bgr))
    text = json.dumps(summary(result, view), indent=2)
    _atomic_write(paths["summary"], text.encode())
    return paths
