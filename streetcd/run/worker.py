"""What a Dask worker does with a batch: crop, read, detect, write, and what it keeps.

:func:`detect_batch` is the Dask task. It runs the batch on this process's
:class:`WorkerRuntime`, the one object that owns everything a worker keeps between batches:
the open tile stores, the segment clouds, the decoded images, the detector's
:class:`~streetcd.detect.cache.SurfaceCache`, and the two helper threads (one decodes the next
view's images and writes the last view's outputs while the detector runs; one crops the next
segment's cloud). It is made on the first batch (or by :func:`warm_worker`) and lives as long
as the worker process; :func:`close_runtime` ends it (tests, a worker that must drop its
caches). Results never depend on what it holds: a batch gives the same records on a fresh
worker and on one that has run the whole city.

Views that fail (corrupt image, no points in view, bad pose) are recorded with the error
and the batch goes on. Only the small :class:`~streetcd.store.records.ViewRecord` s travel back.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import threading
import time
import traceback
from collections import OrderedDict
from collections.abc import Callable, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from functools import partial
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from streetcd.config import RunParams
from streetcd.detect.cache import SurfaceCache
from streetcd.detect.chain import CLASSES_CHECKED, CLOUD_FIELDS, detect_view
from streetcd.detect.regions import Region
from streetcd.errors import InputError, MissingInputError
from streetcd.geometry.frustum import in_frustum
from streetcd.io.images import DEFAULT_MAX_PIXELS, capture_time, fit_view, read_rgb
from streetcd.io.outputs import write_mask, write_overlay
from streetcd.run.plan import Batch, ViewTask, xyz
from streetcd.store.crop import crop_for_view, crop_for_views
from streetcd.store.records import RegionRecord, ViewRecord, camera_json
from streetcd.store.tiles import TileStore
from streetcd.types import Intrinsics, PointCloud, Pose, View

log = logging.getLogger(__name__)

# The last few segment clouds a worker keeps: the segment being worked on, the next one
# being cropped ahead and the one before, which a batch taken late by this worker may still
# need.
SEGMENT_CLOUDS = 3
IMAGES_KEPT = 16  # decoded images (a view is its neighbours' neighbour) and capture times
STORES_KEPT = 4  # open tile stores (store, generation): a new ingest gives a new generation


class FutureCache:
    """The last ``size`` results by key, as futures: a result being made ahead (in a helper
    thread) is waited for, not made twice; an error is kept and raised to every caller."""

    def __init__(self, size: int):
        self.size = size
        self.items: OrderedDict[Any, Future] = OrderedDict()
        self.lock = threading.Lock()

    def claim(self, key: Any) -> tuple[Future, bool]:
        """The entry of ``key`` and whether it is new: whoever gets True must fill it
        (:meth:`fill`)."""
        with self.lock:
            entry = self.items.get(key)
            if entry is not None:
                self.items.move_to_end(key)
                return entry, False
            entry = self.items[key] = Future()
            while len(self.items) > self.size:
                self.items.popitem(last=False)
            return entry, True

    @staticmethod
    def fill(entry: Future, make: Callable[[], Any]) -> None:
        try:
            entry.set_result(make())
        except Exception as exc:  # kept: whoever needs it records the error
            entry.set_exception(exc)

    def get(self, key: Any, make: Callable[[], Any]) -> Any:
        """The result for ``key``, made now (in this thread) unless made or being made."""
        entry, mine = self.claim(key)
        if mine:
            self.fill(entry, make)
        return entry.result()

    def clear(self) -> None:
        with self.lock:
            self.items.clear()


class ImageCache:
    """The last few decoded images and capture times, each read once, ahead of its use in
    the I/O thread (:meth:`prefetch`) or else when first asked for."""

    def __init__(self, io: Callable[[], ThreadPoolExecutor], size: int = IMAGES_KEPT):
        self._io = io
        self.images = FutureCache(size)
        self.times = FutureCache(size)
        self.max_pixels = DEFAULT_MAX_PIXELS  # run.max_image_pixels of the batch at hand

    @staticmethod
    def _key(view: View) -> tuple[Path, tuple[str, float]]:
        if view.image is None:
            raise MissingInputError(f"view {view.name!r} has no image path")
        path = Path(view.image)
        try:
            return path, (str(path), path.stat().st_mtime)
        except FileNotFoundError:
            raise MissingInputError(f"image not found: {path}") from None

    def get(self, view: View) -> np.ndarray:
        """(H, W, 3) uint8 RGB image of ``view``, read-only (:func:`read_rgb`)."""
        path, key = self._key(view)
        limit = self.max_pixels
        return self.images.get((*key, limit), lambda: read_rgb(path, view, limit))

    def captured(self, view: View) -> str | None:
        """:func:`capture_time` of ``view``'s image (None without one)."""
        try:
            path, key = self._key(view)
        except MissingInputError:
            return None if view.image is None else capture_time(Path(view.image))
        return self.times.get(key, lambda: capture_time(path))

    def prefetch(self, task: ViewTask) -> None:
        """Read the capture time of ``task``'s view and decode its and its neighbours'
        images in the I/O thread, ahead of their use; errors are left for the view that
        needs them."""

        def ahead() -> None:
            with contextlib.suppress(Exception):
                self.captured(task.view)
            for v in (task.view, *task.neighbours):
                with contextlib.suppress(Exception):
                    self.get(v)

        self._io().submit(ahead)

    def clear(self) -> None:
        self.images.clear()
        self.times.clear()


class WorkerRuntime:
    """Everything one worker process keeps between batches (see the module docstring)."""

    def __init__(self, surfaces: SurfaceCache | None = None) -> None:
        self.surfaces = surfaces if surfaces is not None else SurfaceCache()
        # the night's input check notes the cloud's classes once (streetcd.run.check); every
        # worker saying it again printed it once per worker
        self.surfaces.first_time(CLASSES_CHECKED)
        self.clouds = FutureCache(SEGMENT_CLOUDS)  # None for a crop that failed
        self.images = ImageCache(self.io_thread)
        self._stores: OrderedDict[tuple[str, int | None], TileStore] = OrderedDict()
        self._threads: dict[str, ThreadPoolExecutor] = {}
        self._lock = threading.Lock()

    # --- what it owns ---------------------------------------------------------------------

    def _thread(self, name: str) -> ThreadPoolExecutor:
        with self._lock:
            pool = self._threads.get(name)
            if pool is None:
                pool = self._threads[name] = ThreadPoolExecutor(1, f"streetcd-{name}")
            return pool

    def io_thread(self) -> ThreadPoolExecutor:
        """Decodes the next view's images (and reads its EXIF) and writes the last view's
        mask and overlay while the detector runs (decoding and encoding run in OpenCV,
        without the GIL), so a worker's core spends its time in the detector."""
        return self._thread("io")

    def crop_thread(self) -> ThreadPoolExecutor:
        """Crops the next segment's cloud (:meth:`crop_ahead`), apart from the I/O thread so
        that the next view's images are not held up behind a crop."""
        return self._thread("crop")

    def store(self, path: str, generation: int | None) -> TileStore:
        """The open TileStore of ``path`` at ``generation`` (a new ingest gives a new
        generation, so a long-lived worker reopens), kept so that its tile cache lives on."""
        key = (path, generation)
        with self._lock:
            store = self._stores.get(key)
            if store is not None:
                self._stores.move_to_end(key)
                return store
        store = TileStore.open(path)
        with self._lock:
            self._stores[key] = store
            while len(self._stores) > STORES_KEPT:
                self._stores.popitem(last=False)
        return store

    def close(self) -> None:
        """Stop the helper threads (after their work) and drop every cache."""
        with self._lock:
            threads, self._threads = list(self._threads.values()), {}
            self._stores.clear()
        for pool in threads:
            pool.shutdown(wait=True)
        self.clouds.clear()
        self.images.clear()
        self.surfaces.clear()

    # --- a batch --------------------------------------------------------------------------

    def detect_batch(
        self, batch: Batch, ahead: Batch | None = None, next_segment: Batch | None = None
    ) -> list[ViewRecord]:
        """Run the detector on every view of ``batch``; one record per view, failures
        included. Masks go under ``out/masks/<segment>/`` atomically. The time this batch
        waited for its crop is work done for its views: it is shared among them in their
        ``total_s`` and ``cpu_s``.

        ahead : the batch this worker is likely to run next (a hint; None when unknown). Its
        first view's images are decoded during this batch's last view, and its segment's
        cloud cropped in the background if it is another segment, so that the next batch
        starts detecting at once. next_segment : the first batch of the worker's next
        segment (a hint): its cloud is cropped in the background while this batch runs.
        Results do not depend on either.
        """
        store = self.store(batch.store, batch.store_generation)
        tasks = batch.tasks
        self.images.max_pixels = batch.config.run.max_image_pixels
        self.images.prefetch(tasks[0])  # found at once when the batch before fetched it ahead
        t0, c0 = time.perf_counter(), time.process_time()
        cloud, _ = self.segment_cloud(batch, store)
        extra_s = time.perf_counter() - t0
        extra_cpu = time.process_time() - c0
        for hint in (ahead, next_segment):
            if hint is not None:
                self.crop_ahead(hint)  # nothing to do when its cloud is made or being made
        done = []
        for k, task in enumerate(tasks):
            if k + 1 < len(tasks):
                self.images.prefetch(tasks[k + 1])
            elif ahead is not None and ahead.tasks:
                self.images.prefetch(ahead.tasks[0])
            done.append(self._detect_one(batch, task, store, cloud, last=k + 1 == len(tasks)))
        t0, c0 = time.perf_counter(), time.process_time()
        records = [_written(record, writing) for record, writing in done]
        extra_s += time.perf_counter() - t0  # what the writes added after the last view
        extra_cpu += time.process_time() - c0
        n = len(records)
        return [
            dataclasses.replace(
                r,
                total_s=(r.total_s or 0.0) + extra_s / n,
                cpu_s=(r.cpu_s or 0.0) + extra_cpu / n,
            )
            for r in records
        ]

    def segment_cloud(self, batch: Batch, store: TileStore) -> tuple[PointCloud | None, bool]:
        """One crop for the views of the batch's segment (and their neighbours), shared by all
        of its batches that run in this process: (cloud or None if the crop failed, whether
        it was made now rather than found or made ahead by :meth:`crop_ahead`, which it
        waits for).

        Sharing one cloud object lets the surface cache build each view's surface once,
        though it serves as the view and as a neighbour of up to three others, across batch
        boundaries too. On failure each view crops on its own, so the error is recorded
        against the views it concerns.
        """
        entry, mine = self.clouds.claim(cloud_key(batch))
        if mine:
            self.clouds.fill(entry, lambda: _crop_segment(batch, store))
        return entry.result(), mine

    def crop_ahead(self, batch: Batch) -> None:
        """Start :meth:`segment_cloud`'s crop for ``batch`` in the crop thread unless it is
        made or being made; :meth:`segment_cloud` then waits for it."""
        entry, mine = self.clouds.claim(cloud_key(batch))
        if mine:

            def crop() -> PointCloud | None:
                return _crop_segment(batch, self.store(batch.store, batch.store_generation))

            self.crop_thread().submit(self.clouds.fill, entry, crop)

    def _detect_one(
        self,
        batch: Batch,
        task: ViewTask,
        store: TileStore,
        shared: PointCloud | None,
        last: bool = False,
    ) -> tuple[ViewRecord, list[Future]]:
        """Detect one view: its record, and the futures of its outputs being written (none
        when there are none) in the I/O thread; the record is good once they are. The
        ``last`` view of a batch, which the batch then waits for, writes its mask in this
        thread while the I/O thread writes its overlay."""
        view, config = task.view, batch.config
        base: dict[str, Any] = dict(
            view=task.key or view.name,
            input_hash=task.input_hash,
            params_hash=batch.params_hash,
            segment_id=task.segment_id,
            center=xyz(view.center),
            image=view.name,
            image_path=None if view.image is None else str(view.image),
            camera=camera_json(view),
        )
        t0, c0 = time.perf_counter(), time.process_time()  # CPU: the process, one view at a time
        try:  # everything a view reads, its EXIF included, fails that view alone
            if view.image is not None:
                base["captured_at"] = self.images.captured(view)  # read ahead in the I/O thread
            image = self.images.get(view)
            # an image of the pose's camera at another resolution: intrinsics rescaled to it
            view = fit_view(view, image.shape[1], image.shape[0])
            neighbours = []
            for n in task.neighbours:
                try:
                    other = self.images.get(n)
                    neighbours.append((other, fit_view(n, other.shape[1], other.shape[0])))
                except (InputError, MissingInputError) as exc:
                    log.warning("view %s: neighbour %s left out: %s", view.name, n.name, exc)
            max_range_m = config.detect.max_range_m
            cloud = (
                shared
                if shared is not None
                else crop_for_view(store, view, max_range_m=max_range_m, fields=CLOUD_FIELDS)
            )
            t1 = time.perf_counter()
            result = detect_view(
                image, view, neighbours, cloud, config.detect, surfaces=self.surfaces
            )
            t2 = time.perf_counter()
            flagged = is_flagged(
                result.changed_fraction,
                [g.pixels for g in result.regions],
                result.mask.size,
                config.run,
                [g.score for g in result.regions],
            )
            mask_path = overlay_path = None
            writing: list[Future] = []
            regions: tuple[RegionRecord, ...] = ()
            if flagged:
                mask_path, overlay_path = output_paths(batch, task)
                write = partial(_write_outputs, mask_path, overlay_path, image, result.mask)
                if last and overlay_path is not None:
                    writing.append(self.io_thread().submit(write, ("overlay",)))
                    writing.append(Future())
                    FutureCache.fill(writing[-1], partial(write, ("mask",)))
                else:
                    writing.append(self.io_thread().submit(write))
                regions = tuple(region_record(g, result.origin) for g in result.regions)
            record = ViewRecord(
                **base,
                status="done",
                flagged=flagged,
                score=float(result.score),
                changed_fraction=float(result.changed_fraction),
                regions=regions,
                mask_path=mask_path,
                overlay_path=overlay_path,
                detect_s=t2 - t1,
                total_s=time.perf_counter() - t0,
                cpu_s=time.process_time() - c0,
            )
            return record, writing
        except Exception as exc:  # a bad view fails alone; the run goes on
            if not isinstance(exc, (InputError, MissingInputError, RuntimeError)):
                log.error("view %s failed unexpectedly:\n%s", view.name, traceback.format_exc())
            message = str(exc) if str(exc) else type(exc).__name__
            failed = ViewRecord(
                **base,
                status="failed",
                error=f"{type(exc).__name__}: {message}",
                total_s=time.perf_counter() - t0,
                cpu_s=time.process_time() - c0,
            )
            return failed, []


# --- the process's runtime ----------------------------------------------------------------

_runtime: WorkerRuntime | None = None
_runtime_lock = threading.Lock()


def worker_runtime() -> WorkerRuntime:
    """This process's :class:`WorkerRuntime`, made on first use."""
    global _runtime
    with _runtime_lock:
        if _runtime is None:
            _runtime = WorkerRuntime()
        return _runtime


def close_runtime() -> None:
    """End this process's runtime (its threads and caches); the next batch makes a new one."""
    global _runtime
    with _runtime_lock:
        runtime, _runtime = _runtime, None
    if runtime is not None:
        runtime.close()


def detect_batch(
    batch: Batch, ahead: Batch | None = None, next_segment: Batch | None = None
) -> list[ViewRecord]:
    """The Dask task: :meth:`WorkerRuntime.detect_batch` on this process's runtime."""
    return worker_runtime().detect_batch(batch, ahead, next_segment)


def warm_worker() -> None:
    """Prepare a Dask worker process before its first batch (``client.run``): make its
    runtime, and keep OpenCV to the worker's one core: a worker thread is a core, and
    OpenCV's own pool would make one worker use two and two workers fight over them.

    Numba's first call in a process sets up LLVM and loads the kernel from its on-disk
    cache; a background thread does that for the crop's kernel, the first one a batch
    calls, and imports PIL for :func:`capture_time`, so that the client need not wait for
    them and the first batch waits at most for what is left (numba's compiler lock, the
    import lock)."""
    cv2.setNumThreads(1)
    worker_runtime()
    threading.Thread(target=_warm_in_background, name="streetcd-warm", daemon=True).start()


def _warm_in_background() -> None:
    """Call the crop's numba kernel once on one point, and import PIL (see
    :func:`warm_worker`)."""
    try:
        view = View("warm-up", Intrinsics(2, 2, 1.0, 1.0, 0.5, 0.5), Pose(np.eye(3), np.zeros(3)))
        in_frustum(np.zeros((1, 3)), view)
        import PIL.Image  # noqa: F401  (only to have it loaded before the first batch)
    except Exception as exc:  # never fails a worker: the first batch does it instead
        log.debug("worker warm-up: %s", exc)


# --- pieces -------------------------------------------------------------------------------


def _written(record: ViewRecord, writing: Sequence[Future]) -> ViewRecord:
    """``record`` once its mask and overlay are on disk; failed (not flagged) if they could
    not be written, so the index never lists a mask that is not there."""
    errors = [exc for exc in (w.exception() for w in writing) if exc is not None]
    if errors:
        exc = errors[0]
        return dataclasses.replace(
            record,
            status="failed",
            error=f"{type(exc).__name__}: cannot write the mask of {record.view}: {exc}",
            flagged=False,
            regions=(),
            mask_path=None,
            overlay_path=None,
        )
    return record


def cloud_key(batch: Batch) -> tuple:
    """The key of a segment's shared crop in a worker's cache: everything the crop depends
    on. The store (path, generation and identity: a store rebuilt at the same path starts its
    generations again), the range, and each view's name, pose and camera: which points a view
    keeps depends on where it is AND where it looks, and on its frustum, so a rerun with
    re-oriented poses on a long-lived cluster must not get the old crop. Exact bytes, not
    rounded: a crop made for other poses is never right."""
    views = batch.crop_views or batch_views(batch)
    return (
        batch.store,
        batch.store_generation,
        batch.store_id,
        batch.segment_id,
        batch.config.detect.max_range_m,
        tuple((v.name, v.pose.R.tobytes(), v.pose.t.tobytes(), v.intrinsics) for v in views),
    )


def _crop_segment(batch: Batch, store: TileStore) -> PointCloud | None:
    """The crop of :meth:`WorkerRuntime.segment_cloud`, None when it fails."""
    views = batch.crop_views or batch_views(batch)
    try:
        return crop_for_views(
            store, list(views), max_range_m=batch.config.detect.max_range_m, fields=CLOUD_FIELDS
        )
    except Exception as exc:  # recorded per view by _detect_one's own crop
        log.warning("segment %s: shared crop failed, cropping per view: %s", batch.segment_id, exc)
        return None


def batch_views(batch: Batch) -> tuple[View, ...]:
    """The views of ``batch`` and their neighbours, by name."""
    views = {t.view.name: t.view for t in batch.tasks}
    views.update({n.name: n for t in batch.tasks for n in t.neighbours})
    return tuple(views[n] for n in sorted(views))


def is_flagged(
    changed_fraction: float,
    region_pixels: Sequence[int],
    n_pixels: int,
    params: RunParams,
    region_scores: Sequence[float] | None = None,
) -> bool:
    """Whether a view goes into the index's flagged list: more than
    ``params.min_changed_fraction`` of its ``n_pixels`` changed and its largest region covers
    at least ``params.min_region_fraction`` of them, a region's size being its pixels (per
    region in ``region_pixels``) × its score (``region_scores``, in [0, 1]; 1 when not given)
    to the power ``params.region_score_power`` (0: pixels alone)."""
    power = params.region_score_power
    if region_scores is None or not power:
        sizes = [float(px) for px in region_pixels]
    else:
        if len(region_scores) != len(region_pixels):
            raise ValueError(f"{len(region_scores)} region scores for {len(region_pixels)} regions")
        sizes = [
            px * min(max(float(sc), 0.0), 1.0) ** power
            for px, sc in zip(region_pixels, region_scores, strict=True)
        ]
    largest = max(sizes, default=0.0)
    return (
        changed_fraction > params.min_changed_fraction
        and largest > 0
        and largest >= params.min_region_fraction * n_pixels
    )


def region_record(g: Region, origin: np.ndarray) -> RegionRecord:
    """A detector Region (local frame) as a RegionRecord in the CRS."""
    o = np.asarray(origin, dtype=np.float64)
    parts = [
        np.asarray(a, dtype=np.float64).reshape(3) + o for a in (g.centroid, g.bbox_min, g.bbox_max)
    ]
    located = all(np.isfinite(p).all() for p in parts)  # else no surface behind it
    c, lo, hi = (xyz(p) if located else None for p in parts)
    return RegionRecord(
        int(g.label),
        int(g.pixels),
        float(g.score),
        c,
        lo,
        hi,
        int(g.dominant_class),
        int(g.foot_class),
        float(g.depth_fraction) if math.isfinite(g.depth_fraction) else None,
    )


def output_paths(batch: Batch, task: ViewTask) -> tuple[str, str | None]:
    """Where the mask PNG and the overlay JPEG (None without overlays) of a view go."""
    stem = Path(task.view.name).stem
    if "#" in task.key:  # the image's hash: names are reused from night to night
        stem += "-" + task.key.rsplit("#", 1)[1]
    folder = Path(batch.out_dir)
    mask_path = folder / "masks" / task.segment_id / f"{stem}.mask.png"
    if not batch.config.run.write_overlays:
        return str(mask_path), None
    return str(mask_path), str(folder / "overlays" / task.segment_id / f"{stem}.overlay.jpg")


def _write_outputs(
    mask_path: str,
    overlay_path: str | None,
    image: np.ndarray,
    mask: np.ndarray,
    parts: tuple[str, ...] = ("mask", "overlay"),
) -> None:
    """Write the ``parts`` named: the mask PNG and the overlay JPEG, each atomically."""
    if "mask" in parts:
        write_mask(Path(mask_path), mask)
    if overlay_path is not None and "overlay" in parts:
        write_overlay(Path(overlay_path), image, mask)
