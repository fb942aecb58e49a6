"""What the detector may keep between calls, passed to it explicitly.

:class:`SurfaceCache` keeps view surfaces (a view is the neighbour of the views around it, so
a segment detected in order would build each surface up to 1 + n_neighbours times) and the
small derived values they are keyed by (the checksum of a read-only image, the cloud's
8-bit colours).

:func:`streetcd.detect.chain.detect_view` is a pure function of its inputs unless a cache is
passed; the result is the same with or without one.
"""

from __future__ import annotations

import weakref
import zlib
from collections import OrderedDict

import numpy as np

from streetcd.config import DetectParams
from streetcd.detect.memo import ArrayMemo
from streetcd.detect.surface import ViewSurface, rgb8
from streetcd.types import PointCloud, View


class SurfaceCache:
    """A small LRU of view surfaces (:func:`streetcd.detect.surface.surface_for_view`), bounded by
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
    :func:`streetcd.store.crop.crop_for_view` does) is a new cloud: no hit, by design, since its
    points differ; surfaces of clouds that have been freed are dropped at the next lookup, so
    such a flow holds no more than the current view's surfaces.
    """

    def __init__(self, max_bytes: int = 448 * 2**20) -> None:
        # default: a 12 MP view and its 3 neighbours (108 MB each with the cloud's colours);
        # with less, detecting one view evicted each surface just before it was needed again
        # (docs/BENCHMARKS.md).
        self.max_bytes = int(max_bytes)
        self._entries: OrderedDict[tuple, tuple[ViewSurface, weakref.ref, weakref.ref]] = (
            OrderedDict()
        )
        self._bytes = 0
        # set by the weak references of the entries' clouds when one is freed: looking for
        # dead entries only then, not at every lookup, spared ~1 ms a lookup with the
        # ~800 small surfaces a worker keeps on 320 px images (docs/BENCHMARKS.md)
        self._a_cloud_died = [False]
        self.hits = 0
        self.misses = 0
        self.checksums = ArrayMemo()  # a read-only image → its CRC-32 (:meth:`checksum`)
        self._rgb8: tuple[weakref.ref, np.ndarray | None] | None = None
        self._told: set[str] = set()

    def key(self, image: np.ndarray, local: View, cloud: PointCloud, params: DetectParams) -> tuple:
        intr, pose = local.intrinsics, local.pose
        return (
            local.name,
            pose.R.tobytes(),
            pose.t.tobytes(),
            intr,
            image.shape,
            self.checksum(image),
            params.zbuffer,
            params.surface,
            params.max_range_m,
            params.classes,  # the class map and its role inference decide the surface's classes
            wants_colour(cloud, params),
            id(cloud.rgb),
            params.appearance.intensity,  # without colours the raster holds intensity, or none
            id(cloud.intensity),
            id(cloud.xyz),
            id(cloud.classification),
            len(cloud.xyz),
            np.asarray(cloud.origin, np.float64).tobytes(),
        )

    def get(self, key: tuple, cloud: PointCloud) -> ViewSurface | None:
        self._drop_dead()
        entry = self._entries.get(key)
        if entry is None or entry[1]() is not cloud.xyz or entry[2]() is not cloud.classification:
            self.misses += 1
            return None
        self._entries.move_to_end(key)
        self.hits += 1
        return entry[0]

    def put(self, key: tuple, cloud: PointCloud, surf: ViewSurface) -> None:
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
        died = self._a_cloud_died

        def note_death(_: weakref.ref) -> None:
            died[0] = True  # a flag, not a bound method: no reference back to the cache

        self._entries[key] = (
            surf,
            weakref.ref(cloud.xyz, note_death),
            weakref.ref(cloud.classification, note_death),
        )
        self._bytes += size
        while self._bytes > self.max_bytes:
            _, (dropped, _, _) = self._entries.popitem(last=False)
            self._bytes -= _surface_bytes(dropped)

    def _drop_dead(self) -> None:
        """Forget surfaces of clouds that no longer exist: they can never hit again (a
        flow that crops a new cloud per view leaves only those behind)."""
        if not self._a_cloud_died[0]:
            return
        self._a_cloud_died[0] = False  # before the scan: a death during it is seen next time
        dead = [k for k, (_, xyz, cls) in self._entries.items() if xyz() is None or cls() is None]
        for k in dead:
            self._bytes -= _surface_bytes(self._entries.pop(k)[0])

    def checksum(self, image: np.ndarray) -> int:
        """CRC-32 of the image's bytes (a few ms per image, mostly reading them).

        For a read-only array that owns its data, which nothing can change, the CRC is kept
        while the array lives: a view and the three views it neighbours then checksum their
        shared image once, not four times. The worker's image reader hands out such arrays
        (:func:`streetcd.io.images.read_rgb`); a writable image is checksummed at every use,
        which costs time, never correctness.
        """
        if not image.flags.writeable and image.flags.owndata:
            return int(self.checksums.get(image, image_crc32))
        return image_crc32(image)

    def cloud_rgb8(self, cloud: PointCloud) -> np.ndarray | None:
        """:func:`cloud_rgb8` of ``cloud.rgb``, kept for the last colour array seen (a weak
        reference: it goes with the cloud), so that a view and its neighbours convert the
        cloud once, not once per surface (two passes over every point). A colour array
        changed *in place* is not noticed, as for surfaces."""
        if cloud.rgb is None:
            return None
        if self._rgb8 is not None and self._rgb8[0]() is cloud.rgb:
            return self._rgb8[1]
        rgb = cloud_rgb8(cloud.rgb)
        self._rgb8 = (weakref.ref(cloud.rgb), rgb)
        return rgb

    def first_time(self, what: str) -> bool:
        """True the first time ``what`` is asked about in this cache's lifetime (a warning
        that holds for every view of a run is said once per cache, not once per view)."""
        if what in self._told:
            return False
        self._told.add(what)
        return True

    def clear(self) -> None:
        self._entries.clear()
        self._bytes = 0
        self._rgb8 = None

    def __len__(self) -> int:
        return len(self._entries)


def image_crc32(image: np.ndarray) -> int:
    """CRC-32 of ``image``'s bytes in C order (any dtype and shape)."""
    return zlib.crc32(np.ascontiguousarray(image).data.cast("B"))


def _surface_bytes(surf: ViewSurface) -> int:
    colour = 0 if surf.colour is None else surf.colour.nbytes
    return surf.depth.nbytes + surf.classes.nbytes + surf.valid.nbytes + colour


def wants_colour(cloud: PointCloud, params: DetectParams) -> bool:
    """Whether surfaces carry the reference colours: the appearance check is on and the
    cloud has colours."""
    return params.appearance.enabled and cloud.rgb is not None


def cloud_rgb8(rgb: np.ndarray) -> np.ndarray | None:
    """A cloud's (N, 3) uint16 colours as (N, 3) uint8 (:func:`streetcd.detect.surface.rgb8`),
    None when all are zero: LAS formats 2, 3, 5, 7, 8 and 10 always have RGB fields, and all
    zero means the writer had no colours, not a black street."""
    out: np.ndarray | None = rgb8(rgb)
    if out is not None and not out.any():
        return None
    return out
