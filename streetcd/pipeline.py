"""The nightly workflow as library functions: plan → detect batches on Dask → publish.

The Prefect flow (``flows/nightly.py``) and the CLI call these; nothing here imports Prefect.

* :func:`plan_run` reads the poses and the images folder, plans street segments, hashes every
  view's inputs and skips the views the index already holds with the same input and
  parameter hashes; it registers the run, the segments and the views that fail before any
  detection (an image without a pose, a pose without an image) in the index.
* :func:`detect_batch` runs on a Dask worker: it crops each view's cloud from the tile store
  itself, reads the images itself, runs the detector and writes masks and overlays
  atomically. Only the small :class:`~streetcd.index.ViewRecord` comes back.
* :class:`streetcd.dispatch.Dispatcher` hands the batches to the workers: each worker a
  share of whole segments (so its tile cache and segment cloud pay), a batch or two at a
  time, each told which batch follows it on that worker so the worker prepares it
  meanwhile; :func:`publish_segment` publishes each batch in one index transaction as it
  ends.
* :func:`run_pipeline` chains them for one run without Prefect (tests, benchmarks).

Views that fail (corrupt image, no points in view, bad pose) are recorded with the error
and the run goes on. A batch lost with its worker is recomputed by Dask elsewhere.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import logging
import os
import threading
import time
import traceback
import uuid
from collections import OrderedDict
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import Future
from dataclasses import dataclass, field
from functools import cached_property, lru_cache, partial
from pathlib import Path
from typing import Any

import numpy as np

from streetcd.errors import CRSMismatchError, InputError, MissingInputError
from streetcd.index import ChangeIndex, RegionRecord, ViewRecord, run_lock
from streetcd.io.las import PointCloud
from streetcd.params import DetectParams, params_to_dict
from streetcd.segments import Segment, SegmentParams, plan_segments
from streetcd.views import View

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png", ".tif", ".tiff")
SCHEDULER_ENV = "STREETCD_SCHEDULER"

# glibc settings for worker processes. Dask's nanny sets MALLOC_TRIM_THRESHOLD_=65536 to
# hand memory back to the OS early; setting any of these variables also freezes glibc's
# mmap threshold at 128 KiB, so every raster of a view (4-24 MB each) is mmapped, faulted
# in page by page and unmapped again: ~57,000 page faults and ~80 ms of kernel time per
# 2 MP view, against ~5,000 and ~25 ms with the settings below (getrusage over the same 24
# views: 384 against 352 ms per view; README, "Speed"). A worker that keeps its last view's
# memory for the next one is what we want; 32 MiB is glibc's largest mmap threshold.
WORKER_MALLOC_ENV = {
    "MALLOC_TRIM_THRESHOLD_": str(1 << 30),
    "MALLOC_MMAP_THRESHOLD_": str(32 << 20),
}


@dataclass(frozen=True)
class PipelineParams:
    """Everything that decides a run's results, besides the inputs.

    batch_size : views per Dask task. Small batches balance the workers at the end of a
        run; they cost little, since the batches of a segment that run on one worker share
        its cloud and surfaces (:func:`segment_cloud`).
    min_changed_fraction : a view is flagged only when more of its pixels than this changed.
    min_region_fraction : ... and when its largest changed region covers at least this share
        of the image (0.2 %: about 4,100 px at 2 MP). Single-view artefacts are small
        scattered regions; on the synthetic streets the largest region of an unchanged view
        covers at most 0.17 % (docs/TUNING.md, "Which views are flagged").
    write_overlays : also write a JPEG of the image with the mask tinted red.
    """

    detect: DetectParams = field(default_factory=DetectParams)
    segments: SegmentParams = field(default_factory=SegmentParams)
    batch_size: int = 4
    min_changed_fraction: float = 0.0
    min_region_fraction: float = 0.002
    write_overlays: bool = True

    def __post_init__(self) -> None:
        if self.batch_size < 1:
            raise InputError(f"batch_size = {self.batch_size} must be >= 1")
        if not 0.0 <= self.min_changed_fraction < 1.0:
            raise InputError(
                f"min_changed_fraction = {self.min_changed_fraction} must be in [0, 1)"
            )
        if not 0.0 <= self.min_region_fraction < 1.0:
            raise InputError(f"min_region_fraction = {self.min_region_fraction} must be in [0, 1)")

    def hash(self) -> str:
        """16 hex digits over every parameter that changes a view's result or its segment."""
        blob = {
            "detect": params_to_dict(self.detect),
            "segments": dataclasses.asdict(self.segments),
            "min_changed_fraction": self.min_changed_fraction,
            "min_region_fraction": self.min_region_fraction,
            "write_overlays": self.write_overlays,
        }
        return hashlib.sha256(json.dumps(blob, sort_keys=True).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class ViewTask:
    """One view's work: the view (pose in the CRS, image path), its neighbours, its hash."""

    view: View
    neighbours: tuple[View, ...]
    segment_id: str
    input_hash: str


@dataclass(frozen=True)
class Batch:
    """Consecutive views of one segment, processed by one Dask task.

    crop_views : the views whose clouds the segment's batches share: every view of the
        segment still to do, and its neighbours. All batches of a segment carry the same
        tuple, so a worker crops the segment once (:func:`segment_cloud`) and serves its
        later batches, and the detector's surface cache, from that one cloud.
    store_generation : the tile store's generation at planning, so a long-lived worker
        never reads a store it opened before the last ingest.
    part : set on the single-view batches a batch was cut into (the end of a worker's
        queue, :func:`streetcd.dispatch.split_tail`): the view's position in the batch.
    """

    segment_id: str
    number: int
    tasks: tuple[ViewTask, ...]
    store: str
    out_dir: str
    params: PipelineParams
    params_hash: str
    crop_views: tuple[View, ...] = ()
    store_generation: int | None = None
    part: int | None = None

    @property
    def key(self) -> str:
        tail = "" if self.part is None else f".{self.part}"
        return f"detect-{self.segment_id}-{self.number}{tail}"


@dataclass(frozen=True)
class Plan:
    """What a run will do. ``batches`` hold only the views still to process."""

    run_id: str
    index: str
    crs: str | None
    segments: tuple[Segment, ...]
    batches: tuple[Batch, ...]
    n_views: int
    n_skipped: int
    failed_at_plan: tuple[tuple[str, str], ...]  # (view, error) of views failed in planning
    params_hash: str

    @property
    def n_todo(self) -> int:
        return sum(len(b.tasks) for b in self.batches)

    def batches_of(self, segment_id: str) -> tuple[Batch, ...]:
        return self._by_segment.get(segment_id, ())

    @property
    def segments_todo(self) -> tuple[str, ...]:
        """Ids of the segments with views to do, in plan (trajectory) order."""
        return tuple(self._by_segment)

    def order(self, batch: Batch) -> int:
        """Position of ``batch`` (or of the batch it is a part of) in :attr:`batches`:
        segments in plan order, each one's batches in trajectory order (the order a worker
        should run them in)."""
        return self._order[batch.segment_id, batch.number]

    @cached_property
    def _order(self) -> dict[tuple[str, int], int]:
        return {(b.segment_id, b.number): k for k, b in enumerate(self.batches)}

    @cached_property
    def _by_segment(self) -> dict[str, tuple[Batch, ...]]:
        # Built once: a city's plan has thousands of segments, asked for one by one.
        out: dict[str, list[Batch]] = {}
        for b in self.batches:
            out.setdefault(b.segment_id, []).append(b)
        return {k: tuple(v) for k, v in out.items()}


@dataclass
class RunSummary:
    """Counts and times of one run: ``detect_s`` the sum of per-view detector times,
    ``view_s`` of the time each view held its worker's detection thread (the detector and
    whatever it waited for: its images, its share of the segment's crop and of its batch's
    last writes; what the worker's I/O and crop threads did ahead is not in it), ``cpu_s``
    the worker process's CPU time meanwhile;
    ``plan_s`` the planning, ``wait_s`` the time spent waiting for the Dask cluster after
    planning, ``wall_s`` the whole run."""

    run_id: str
    n_views: int = 0
    n_skipped: int = 0
    n_done: int = 0
    n_failed: int = 0
    n_flagged: int = 0
    n_lost: int = 0  # views of batches that never came back (not published; next run retries)
    detect_s: float = 0.0
    view_s: float = 0.0
    cpu_s: float = 0.0
    plan_s: float = 0.0
    wait_s: float = 0.0
    wall_s: float = 0.0
    failures: list[tuple[str, str]] = field(default_factory=list)

    def add(self, records: Sequence[ViewRecord]) -> None:
        for r in records:
            if r.status == "done":
                self.n_done += 1
            else:
                self.n_failed += 1
                self.failures.append((r.view, r.error or ""))
            self.n_flagged += int(r.flagged)
            self.detect_s += r.detect_s or 0.0
            self.view_s += r.total_s or 0.0
            self.cpu_s += r.cpu_s or 0.0

    def merge(self, other: RunSummary) -> None:
        for name in ("n_done", "n_failed", "n_flagged", "n_lost", "detect_s", "view_s", "cpu_s"):
            setattr(self, name, getattr(self, name) + getattr(other, name))
        self.failures += other.failures

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


# --- progress -----------------------------------------------------------------------------

Listener = Callable[[str, Any], None]
_listeners: list[Listener] = []
_listeners_lock = threading.Lock()


@contextlib.contextmanager
def progress_listener(fn: Listener) -> Iterator[None]:
    """Call ``fn(event, payload)`` on progress, in this process: ``("planned", Plan)`` once
    planning is done, ``("batch", list[ViewRecord])`` after each batch is published.

    The CLI draws its progress bar with this while the flow runs; the flow knows nothing of it.
    """
    with _listeners_lock:
        _listeners.append(fn)
    try:
        yield
    finally:
        with _listeners_lock:
            _listeners.remove(fn)


def _notify(event: str, payload: Any) -> None:
    with _listeners_lock:
        listeners = list(_listeners)
    for fn in listeners:
        fn(event, payload)


# --- hashing ------------------------------------------------------------------------------


def file_hash(path: Path, chunk: int = 1 << 20) -> str:
    """SHA-256 (16 hex digits) of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()[:16]


def _view_key(view: View, image_hash: str) -> str:
    i = view.intrinsics
    pose = np.concatenate([view.pose.R.ravel(), view.pose.t]).round(9)
    return (
        f"{view.name}|{image_hash}|{pose.tolist()}|{i.width},{i.height},{i.fx!r},{i.fy!r},"
        f"{i.cx!r},{i.cy!r},{list(i.dist)}"
    )


def tiles_fingerprint(store: Any, center: np.ndarray, radius_m: float) -> str:
    """Hash of the tiles (id, fragments, counts) within ``radius_m`` of ``center`` (CRS).

    The view's cloud is cropped from a subset of these (the frustum is range-limited), so
    ingesting a new MLS file changes the hash of exactly the views it can affect.
    """
    c = np.asarray(center, dtype=np.float64)
    tiles = store.tiles_in_bbox(c[0] - radius_m, c[1] - radius_m, c[0] + radius_m, c[1] + radius_m)
    parts = sorted(f"{t.id}:" + ",".join(f"{f.key}/{f.count}" for f in t.fragments) for t in tiles)
    return _hash_text(";".join(parts))


# --- planning -----------------------------------------------------------------------------


def list_images(folder: str | Path) -> dict[str, Path]:
    """{file name: path} of the images directly in ``folder``."""
    folder = Path(folder)
    if not folder.is_dir():
        raise MissingInputError(f"images folder not found: {folder}")
    return {
        p.name: p
        for p in sorted(folder.iterdir())
        if p.is_file() and p.suffix.lower() in IMAGE_SUFFIXES
    }


def plan_run(
    images: str | Path,
    poses: str | Path,
    store: str | Path,
    index: str | Path,
    out: str | Path,
    params: PipelineParams = PipelineParams(),
    *,
    retry_failed: bool = False,
    run_id: str | None = None,
) -> Plan:
    """Plan a run and register it in the index (run row, segments, plan-time failures).

    images : folder of the new images. poses : a pose file (COLMAP or OPK CSV) naming them.
    store : the tile store of the reference cloud. out : where masks and overlays go.
    A view is skipped when the index holds it with the same input and parameter hashes
    (``done``, or ``failed`` unless ``retry_failed``).
    """
    from streetcd.io.las import crs_string
    from streetcd.io.poses import read_poses
    from streetcd.tiles import TileStore

    run_id = run_id or time.strftime("%Y%m%dT%H%M%S") + "-" + uuid.uuid4().hex[:6]
    # Workers run elsewhere (another cwd, another machine with the same mounts): absolute paths.
    images, poses, store, out = (Path(p).resolve() for p in (images, poses, store, out))
    files = list_images(images)
    bad_rows: list[tuple[str, str]] = []
    pose_set = read_poses(poses, image_dir=images, bad_rows=bad_rows)
    tile_store = TileStore.open(store)
    crs = crs_string(pose_set.crs) if pose_set.crs else None
    store_crs = crs_string(tile_store.crs) if tile_store.crs else None
    if crs and store_crs and crs != store_crs:
        raise CRSMismatchError(f"poses {poses} are in {crs}, tile store {store} in {store_crs}")
    crs = crs or store_crs
    reach_m = params.detect.max_range_m + 2.0  # crop buffer (1 m) and some slack
    generation = tile_store.index.get("generation")
    phash = params.hash()

    posed_twice = _posed_twice([v.name for v in pose_set.views] + [n for n, _ in bad_rows])
    failed = _bad_pose_records(bad_rows, posed_twice, files, phash)
    failed += [
        ViewRecord(
            name,
            _hash_text(f"{name}|posed {n} times|" + _file_hash_or(files.get(name), "missing")),
            phash,
            None,
            "failed",
            f"InputError: {poses}: view {name!r} has {n} poses; keep one",
        )
        for name, n in posed_twice.items()
    ]
    views: list[View] = []
    for v in pose_set.views:
        if v.name in posed_twice:
            continue
        if v.image is not None and v.image.name in files:
            views.append(v)
        else:
            failed.append(
                ViewRecord(
                    v.name,
                    _hash_text(_view_key(v, "missing")),
                    phash,
                    None,
                    "failed",
                    f"image not found: {Path(images) / v.name}",
                    center=_xyz(v.center),
                )
            )
    posed = {v.image.name for v in views if v.image is not None}
    posed |= {r.view for r in failed}  # a bad or repeated pose row already failed its image
    for name, path in files.items():
        if name not in posed:
            failed.append(
                ViewRecord(
                    name,
                    file_hash(path),
                    phash,
                    None,
                    "failed",
                    f"no pose for image {name} in {poses}",
                )
            )

    image_hash = {v.name: file_hash(v.image) for v in views if v.image is not None}
    by_name = {v.name: v for v in views}
    segments = plan_segments(views, params.segments)

    with ChangeIndex(index) as idx:
        idx.set_crs(crs)
        known = idx.processed()

        def skip(name: str, input_hash: str) -> bool:
            have = known.get(name)
            return (
                have is not None
                and have[:2] == (input_hash, phash)
                and (have[2] == "done" or not retry_failed)
            )

        batches, n_skipped = [], 0
        for seg in segments:
            todo = []
            for name, nbrs in zip(seg.views, seg.neighbours, strict=True):
                v = by_name[name]
                parts = [
                    _view_key(v, image_hash[name]),
                    tiles_fingerprint(tile_store, v.center, reach_m),
                ]
                parts += [_view_key(by_name[n], image_hash[n]) for n in nbrs]
                h = _hash_text("\n".join(parts))
                if skip(name, h):
                    n_skipped += 1
                else:
                    todo.append(ViewTask(v, tuple(by_name[n] for n in nbrs), seg.id, h))
            crop_views = {t.view.name: t.view for t in todo}
            crop_views.update({n.name: n for t in todo for n in t.neighbours})
            for k in range(0, len(todo), params.batch_size):
                batches.append(
                    Batch(
                        seg.id,
                        k // params.batch_size,
                        tuple(todo[k : k + params.batch_size]),
                        str(store),
                        str(out),
                        params,
                        phash,
                        tuple(crop_views[n] for n in sorted(crop_views)),
                        generation,
                    )
                )
        new_failed = [r for r in failed if not skip(r.view, r.input_hash)]
        n_skipped += len(failed) - len(new_failed)
        idx.begin_run(
            run_id,
            phash,
            {"images": str(images), "poses": str(poses), "store": str(store), "out": str(out)},
        )
        idx.add_segments(segments, run_id)
        if new_failed:
            idx.publish(run_id, new_failed)
    plan = Plan(
        run_id,
        str(index),
        crs,
        tuple(segments),
        tuple(batches),
        len(views) + len(failed),
        n_skipped,
        tuple((r.view, r.error or "") for r in new_failed),
        phash,
    )
    _notify("planned", plan)
    return plan


def _bad_pose_records(
    bad_rows: Sequence[tuple[str, str]],
    posed_twice: dict[str, int],
    files: dict[str, Path],
    phash: str,
) -> list[ViewRecord]:
    """A failed record for each malformed pose row (its error names the file, line and
    field). Its input hash covers the error and the image, so fixing the row, or the image,
    makes the view due again. A name with more than one row fails as a repeat instead."""
    out = []
    for name, error in bad_rows:
        if name in posed_twice:
            continue
        key = f"{name}|{error}|{_file_hash_or(files.get(name), 'missing')}"
        out.append(ViewRecord(name, _hash_text(key), phash, None, "failed", f"InputError: {error}"))
    return out


def _posed_twice(names: Sequence[str]) -> dict[str, int]:
    """{name: count} of the view names with more than one pose row (good or bad): which
    pose is meant cannot be known, so such a view fails (rather than the whole run)."""
    counts: dict[str, int] = {}
    for name in names:
        counts[name] = counts.get(name, 0) + 1
    return {name: n for name, n in counts.items() if n > 1}


def _file_hash_or(path: Path | None, default: str) -> str:
    return file_hash(path) if path is not None else default


def _xyz(a: np.ndarray) -> tuple[float, float, float]:
    return float(a[0]), float(a[1]), float(a[2])


def _hash_text(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()[:16]


# --- on a worker --------------------------------------------------------------------------


@lru_cache(maxsize=4)
def _open_store(path: str, generation: int | None = None) -> Any:
    """One open TileStore per worker process, store and store generation (a new ingest
    gives a new generation, so a long-lived worker reopens), so its tile cache lives on."""
    from streetcd.tiles import TileStore

    return TileStore.open(path)


def warm_worker() -> None:
    """Prepare a Dask worker process before its first batch (``client.run``): import the
    detector's modules, so that the first batch does not pay for it, and keep OpenCV to the
    worker's one core: a worker thread is a core, and OpenCV's own pool would make one
    worker use two and two workers fight over them.

    Numba's first call in a process sets up LLVM and loads the kernel from its on-disk
    cache (~0.3 s); a background thread does that for the crop's kernel, the first one a
    batch calls, and imports PIL for :func:`capture_time`, so that the client need not wait
    for them and the first batch waits at most for what is left (numba's compiler lock, the
    import lock)."""
    import cv2

    import streetcd.crop
    import streetcd.detect  # noqa: F401

    cv2.setNumThreads(1)
    threading.Thread(target=_warm_in_background, name="streetcd-warm", daemon=True).start()


def _warm_in_background() -> None:
    """Call the crop's numba kernel once on one point, and import PIL (see
    :func:`warm_worker`)."""
    from streetcd.camera import Intrinsics, Pose
    from streetcd.crop import in_frustum

    try:
        view = View("warm-up", Intrinsics(2, 2, 1.0, 1.0, 0.5, 0.5), Pose(np.eye(3), np.zeros(3)))
        in_frustum(np.zeros((1, 3)), view)
        import PIL.Image  # noqa: F401
    except Exception as exc:  # never fails a worker: the first batch does it instead
        log.debug("worker warm-up: %s", exc)


class _FutureCache:
    """The last ``size`` results of this process by key, as futures: a result being made
    ahead (in the I/O or crop thread) is waited for, not made twice; an error is kept and
    raised to every caller."""

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


class _ImageCache:
    """The last few decoded images of this process (a view is its neighbours' neighbour),
    and the capture times of the last few views, each read once, ahead of its use in the
    I/O thread (:meth:`prefetch`) or else when first asked for."""

    def __init__(self, size: int = 16):
        self.images = _FutureCache(size)
        self.times = _FutureCache(size)

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
        """(H, W, 3) uint8 RGB image of ``view`` (:func:`read_rgb`)."""
        path, key = self._key(view)
        return self.images.get(key, lambda: read_rgb(path, view))

    def captured(self, view: View) -> str | None:
        """:func:`capture_time` of ``view``'s image (None without one)."""
        try:
            path, key = self._key(view)
        except MissingInputError:
            return None if view.image is None else capture_time(Path(view.image))
        return self.times.get(key, lambda: capture_time(path))

    def prefetch(self, task: ViewTask) -> None:
        """Read the capture time of ``task``'s view and decode its and its neighbours'
        images in this process's I/O thread, ahead of their use; errors are left for the
        view that needs them."""

        def ahead() -> None:
            with contextlib.suppress(Exception):
                self.captured(task.view)
            for v in (task.view, *task.neighbours):
                with contextlib.suppress(Exception):
                    self.get(v)

        _io_thread().submit(ahead)

    def clear(self) -> None:
        self.images.clear()
        self.times.clear()


_images = _ImageCache()


@lru_cache(maxsize=1)
def _io_thread() -> Any:
    """This process's I/O thread: it decodes the next view's images (and reads its EXIF)
    and writes the last view's mask and overlay while the detector runs (decoding and
    encoding run in OpenCV, without the GIL), so a worker's core spends its time in the
    detector."""
    from concurrent.futures import ThreadPoolExecutor

    return ThreadPoolExecutor(1, thread_name_prefix="streetcd-io")


@lru_cache(maxsize=1)
def _crop_thread() -> Any:
    """This process's thread for the next segment's crop (:func:`crop_ahead`), apart from
    the I/O thread so that the next view's images are not held up behind a crop."""
    from concurrent.futures import ThreadPoolExecutor

    return ThreadPoolExecutor(1, thread_name_prefix="streetcd-crop")


EXIF_IFD = 0x8769
DATE_TIME_ORIGINAL = 36867  # EXIF "YYYY:MM:DD HH:MM:SS", the camera's clock
OFFSET_TIME_ORIGINAL = 36881  # EXIF 2.31 "+HH:MM", that clock's offset from UTC


def capture_time(path: Path) -> str | None:
    """When the image at ``path`` was taken, as an index timestamp (UTC), or None.

    From EXIF ``DateTimeOriginal``, shifted by ``OffsetTimeOriginal`` where given; without
    an offset the camera clock is taken as UTC (survey cameras run on GPS/UTC time). Pose
    files give only a number of seconds whose epoch (GPS week, GPS, Unix) they do not
    state, so they are not used. Reads the header only; never fails (None instead).
    """
    from datetime import UTC, datetime

    from PIL import Image

    try:
        with Image.open(path) as image:
            exif = image.getexif().get_ifd(EXIF_IFD)
        text = str(exif.get(DATE_TIME_ORIGINAL, "")).strip().rstrip("\x00")
        if not text:
            return None
        when = datetime.strptime(text, "%Y:%m:%d %H:%M:%S")
        offset = str(exif.get(OFFSET_TIME_ORIGINAL, "")).strip().rstrip("\x00")
        if offset:
            when = datetime.fromisoformat(when.isoformat() + offset)
        else:
            when = when.replace(tzinfo=UTC)
    except (OSError, ValueError, SyntaxError) as exc:  # no EXIF, or a malformed date
        log.debug("%s: no capture time: %s", path, exc)
        return None
    return when.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")


def read_rgb(path: Path, view: View) -> np.ndarray:
    """(H, W, 3) uint8 RGB image of ``view``, read-only (the image cache shares it among the
    views of a batch, and the surface cache keys it by a checksum computed once,
    :func:`streetcd.detect.image_checksum`); errors name the file."""
    from streetcd.detect import decode_rgb

    rgb = decode_rgb(path, np.fromfile(path, dtype=np.uint8))
    h, w = rgb.shape[:2]
    i = view.intrinsics
    if (w, h) != (i.width, i.height):
        raise InputError(
            f"{path}: image is {w}x{h} but the pose of {view.name!r} says {i.width}x{i.height}"
        )
    rgb.flags.writeable = False
    return rgb


def detect_batch(
    batch: Batch, ahead: Batch | None = None, next_segment: Batch | None = None
) -> list[ViewRecord]:
    """Run the detector on every view of ``batch``; one record per view, failures included.

    Runs on a Dask worker: opens the tile store (cached per process), crops the segment's
    cloud (cached per process), reads the images, writes masks under
    ``out/masks/<segment>/`` atomically. The time this batch waited for its crop is work
    done for its views: it is shared among them in their ``total_s`` and ``cpu_s``.

    ahead : the batch this worker is likely to run next (a hint; None when unknown). Its
    first view's images are decoded during this batch's last view, and its segment's
    cloud cropped in the background if it is another segment, so that the next batch starts
    detecting at once. next_segment : the first batch of the worker's next segment (a
    hint): its cloud is cropped in the background while this batch runs. Results do not
    depend on either.
    """
    store = _open_store(batch.store, batch.store_generation)
    tasks = batch.tasks
    _images.prefetch(tasks[0])  # found at once when the batch before fetched it ahead
    t0, c0 = time.perf_counter(), time.process_time()
    cloud, _ = segment_cloud(batch, store)
    extra_s = time.perf_counter() - t0
    extra_cpu = time.process_time() - c0
    for hint in (ahead, next_segment):
        if hint is not None:
            crop_ahead(hint)  # nothing to do when its cloud is made or being made
    done = []
    for k, task in enumerate(tasks):
        if k + 1 < len(tasks):
            _images.prefetch(tasks[k + 1])
        elif ahead is not None and ahead.tasks:
            _images.prefetch(ahead.tasks[0])
        done.append(_detect_one(batch, task, store, cloud, last=k + 1 == len(tasks)))
    t0, c0 = time.perf_counter(), time.process_time()
    records = [_written(record, writing) for record, writing in done]
    extra_s += time.perf_counter() - t0  # what the writes added after the last view
    extra_cpu += time.process_time() - c0
    n = len(records)
    return [
        dataclasses.replace(
            r, total_s=(r.total_s or 0.0) + extra_s / n, cpu_s=(r.cpu_s or 0.0) + extra_cpu / n
        )
        for r in records
    ]


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


# The last few segment clouds of this process, keyed by store, generation, segment and
# crop views. Three: the segment being worked on, the next one being cropped ahead
# (:func:`crop_ahead`) and the one before, which a batch stolen late by this worker may
# still need. None for a crop that failed.
_clouds = _FutureCache(3)


def _cloud_key(batch: Batch) -> tuple:
    views = batch.crop_views or _batch_views(batch)
    return (
        batch.store,
        batch.store_generation,
        batch.segment_id,
        batch.params.detect.max_range_m,
        tuple(v.name for v in views),
    )


def _crop_segment(batch: Batch, store: Any) -> PointCloud | None:
    """The crop of :func:`segment_cloud`, None when it fails."""
    from streetcd.crop import crop_for_views

    views = batch.crop_views or _batch_views(batch)
    try:
        return crop_for_views(store, list(views), max_range_m=batch.params.detect.max_range_m)
    except Exception as exc:  # recorded per view by _detect_one's own crop
        log.warning("segment %s: shared crop failed, cropping per view: %s", batch.segment_id, exc)
        return None


def segment_cloud(batch: Batch, store: Any) -> tuple[PointCloud | None, bool]:
    """One crop for the views of the batch's segment (and their neighbours), shared by all
    of its batches that run in this process: (cloud or None if the crop failed, whether it
    was made now rather than found or made ahead by :func:`crop_ahead`, which it waits for).

    Sharing one cloud object lets the detector's surface cache build each view's surface
    once, though it serves as the view and as a neighbour of up to three others, across
    batch boundaries too. On failure each view crops on its own, so the error is recorded
    against the views it concerns.
    """
    entry, mine = _clouds.claim(_cloud_key(batch))
    if mine:
        _clouds.fill(entry, lambda: _crop_segment(batch, store))
    return entry.result(), mine


def crop_ahead(batch: Batch) -> None:
    """Start the crop of :func:`segment_cloud` for ``batch`` in this process's crop thread
    unless it is made or being made; :func:`segment_cloud` then waits for it."""
    entry, mine = _clouds.claim(_cloud_key(batch))
    if mine:

        def crop() -> PointCloud | None:
            return _crop_segment(batch, _open_store(batch.store, batch.store_generation))

        _crop_thread().submit(_clouds.fill, entry, crop)


def _batch_views(batch: Batch) -> tuple[View, ...]:
    views = {t.view.name: t.view for t in batch.tasks}
    views.update({n.name: n for t in batch.tasks for n in t.neighbours})
    return tuple(views[n] for n in sorted(views))


def _detect_one(
    batch: Batch, task: ViewTask, store: Any, shared: PointCloud | None, last: bool = False
) -> tuple[ViewRecord, list[Future]]:
    """Detect one view: its record, and the futures of its outputs being written (none
    when there are none) in the I/O thread; the record is good once they are. The
    ``last`` view of a batch, which the batch then waits for, writes its mask in this
    thread while the I/O thread writes its overlay."""
    from streetcd.crop import crop_for_view
    from streetcd.detect import detect_view

    view, p = task.view, batch.params
    base: dict[str, Any] = dict(
        view=view.name,
        input_hash=task.input_hash,
        params_hash=batch.params_hash,
        segment_id=task.segment_id,
        center=_xyz(view.center),
    )
    t0, c0 = time.perf_counter(), time.process_time()  # CPU time: the process, one view at a time
    if view.image is not None:
        base["captured_at"] = _images.captured(view)  # read ahead in the I/O thread
    try:
        image = _images.get(view)
        neighbours = []
        for n in task.neighbours:
            try:
                neighbours.append((_images.get(n), n))
            except (InputError, MissingInputError) as exc:
                log.warning("view %s: neighbour %s left out: %s", view.name, n.name, exc)
        cloud = (
            shared
            if shared is not None
            else crop_for_view(store, view, max_range_m=p.detect.max_range_m)
        )
        t1 = time.perf_counter()
        result = detect_view(image, view, neighbours, cloud, p.detect)
        t2 = time.perf_counter()
        flagged = is_flagged(
            result.changed_fraction, [g.pixels for g in result.regions], result.mask.size, p
        )
        mask_path = overlay_path = None
        writing: list[Future] = []
        regions: tuple[RegionRecord, ...] = ()
        if flagged:
            mask_path, overlay_path = _output_paths(batch, task)
            write = partial(_write_outputs, batch, task, image, result.mask)
            if last and overlay_path is not None:
                writing.append(_io_thread().submit(write, ("overlay",)))
                writing.append(Future())
                _FutureCache.fill(writing[-1], partial(write, ("mask",)))
            else:
                writing.append(_io_thread().submit(write))
            regions = tuple(_region_record(g, result.origin) for g in result.regions)
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


def is_flagged(
    changed_fraction: float, region_pixels: Sequence[int], n_pixels: int, params: PipelineParams
) -> bool:
    """Whether a view goes into the index's flagged list: more than
    ``params.min_changed_fraction`` of its ``n_pixels`` changed and its largest region (pixels
    per region in ``region_pixels``) covers at least ``params.min_region_fraction`` of them."""
    largest = max(region_pixels, default=0)
    return (
        changed_fraction > params.min_changed_fraction
        and largest > 0
        and largest >= params.min_region_fraction * n_pixels
    )


def _region_record(g: Any, origin: np.ndarray) -> RegionRecord:
    """A detector Region (local frame) as a RegionRecord in the CRS."""
    o = np.asarray(origin, dtype=np.float64)
    parts = [
        np.asarray(a, dtype=np.float64).reshape(3) + o for a in (g.centroid, g.bbox_min, g.bbox_max)
    ]
    located = all(np.isfinite(p).all() for p in parts)  # else no surface behind it
    c, lo, hi = (_xyz(p) if located else None for p in parts)
    return RegionRecord(
        int(g.label), int(g.pixels), float(g.score), c, lo, hi, int(g.dominant_class)
    )


def _output_paths(batch: Batch, task: ViewTask) -> tuple[str, str | None]:
    """Where the mask PNG and the overlay JPEG (None without overlays) of a view go."""
    stem = Path(task.view.name).stem
    folder = Path(batch.out_dir)
    mask_path = folder / "masks" / task.segment_id / f"{stem}.mask.png"
    if not batch.params.write_overlays:
        return str(mask_path), None
    return str(mask_path), str(folder / "overlays" / task.segment_id / f"{stem}.overlay.jpg")


def _write_outputs(
    batch: Batch,
    task: ViewTask,
    image: np.ndarray,
    mask: np.ndarray,
    parts: tuple[str, ...] = ("mask", "overlay"),
) -> None:
    """Write ``mask`` (H, W) bool as a 0/255 PNG, and the overlay JPEG, atomically (the
    ``parts`` named)."""
    import cv2

    mask_path, overlay_path = _output_paths(batch, task)
    if "mask" in parts:
        _atomic_write(Path(mask_path), _encode(".png", mask.astype(np.uint8) * 255))
    if overlay_path is None or "overlay" not in parts:
        return
    bgr = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)  # a copy, tinted in place
    _tint_red(bgr, mask, channel=2)
    _atomic_write(Path(overlay_path), _encode(".jpg", bgr))


def _tint_red(image: np.ndarray, mask: np.ndarray, channel: int = 0) -> np.ndarray:
    """Blend ``image`` (H, W, 3) uint8 C-contiguous, in place, half-way to pure red where
    ``mask`` (H, W) bool is set: ``⌊(v + 255) / 2⌋`` in the red ``channel`` (0 for RGB, 2 for BGR),
    ``⌊v / 2⌋`` in the others (the overlay's ``0.5 v + 0.5 red``, truncated). A lookup
    table and a masked copy in OpenCV, which lets the detector have the GIL meanwhile."""
    import cv2

    pick = np.ascontiguousarray(mask, dtype=bool).view(np.uint8)
    # Only the box around the mask: changes are a few per cent of a view, and the lookup
    # over the whole image was half of the overlay's cost.
    x, y, w, h = cv2.boundingRect(pick)
    if w and h:
        box = image[y : y + h, x : x + w]
        cv2.copyTo(cv2.LUT(box, _half_red_lut(channel)), pick[y : y + h, x : x + w], box)
    return image


@lru_cache(maxsize=3)
def _half_red_lut(channel: int) -> np.ndarray:
    """(256, 1, 3) uint8 table of :func:`_tint_red` for red in ``channel``."""
    v = np.arange(256, dtype=np.uint16)
    lut = np.stack([v >> 1] * 3, axis=-1)
    lut[:, channel] = (v + 255) >> 1
    return lut.astype(np.uint8).reshape(256, 1, 3)


def _encode(ext: str, array: np.ndarray) -> bytes:
    import cv2

    ok, buf = cv2.imencode(ext, array)
    if not ok:
        raise InputError(f"cannot encode a {array.shape} array as {ext}")
    return buf.tobytes()


def _atomic_write(path: Path, data: bytes) -> None:
    """Write under a temporary name in the same folder, then rename over ``path``."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.{threading.get_ident()}.tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
    os.replace(tmp, path)


# --- on the client ------------------------------------------------------------------------


@contextlib.contextmanager
def dask_client(
    scheduler: str | None = None, workers: int = 2, threads_per_worker: int = 1
) -> Iterator[Any]:
    """A ``distributed.Client``: to ``scheduler`` (or ``$STREETCD_SCHEDULER``) when given,
    else to a new LocalCluster of ``workers`` processes that is closed afterwards."""
    import dask
    from distributed import Client, LocalCluster

    address = scheduler or os.environ.get(SCHEDULER_ENV) or None
    if address:
        with Client(address, set_as_default=False) as client:
            yield client
        return
    if workers < 1:
        raise InputError(f"workers = {workers} must be >= 1")
    # dashboard on a free port: ``None`` would still bind 8787 and warn when it is taken.
    with (
        dask.config.set(local_worker_config()),
        LocalCluster(
            n_workers=workers,
            threads_per_worker=threads_per_worker,
            processes=True,
            dashboard_address=":0",
        ) as cluster,
        Client(cluster, set_as_default=False) as client,
    ):
        yield client


# Dask's periodic housekeeping, slowed down: an idle LocalCluster of 2 workers took 4.5 %
# of a core with the defaults (an event-loop tick every 20 ms and a memory check every
# 100 ms in every process, a system monitor every 0.5 s) and 2.4 % with these; on a
# 2-core machine that CPU comes out of the detectors' share. The tick only measures how
# long the event loop was blocked, and the system monitor only feeds the dashboard.
# The worker's statistical profiler (the dashboard's "Profile" page) is off: it wakes the
# worker's event loop every 10 ms to walk the running task's stack under the GIL, 1 s of CPU
# per 50 s of detection; with 2 workers on 2 cores a 200-view run took 50.2 s with it and
# 49.0 s without (medians of 3, alternated). Turn it back on to profile a worker.
QUIET_DASK = {
    "distributed.admin.tick.interval": "1s",
    "distributed.admin.system-monitor.interval": "5s",
    "distributed.worker.memory.monitor-interval": "1s",
    "distributed.worker.profile.enabled": False,
}


def local_worker_config() -> dict[str, Any]:
    """Dask settings for our LocalCluster (``infra/dask.yaml`` has the same for workers
    started by hand): the malloc environment of :data:`WORKER_MALLOC_ENV` and
    :data:`QUIET_DASK`."""
    env = {f"distributed.nanny.pre-spawn-environ.{k}": v for k, v in WORKER_MALLOC_ENV.items()}
    return {**env, **QUIET_DASK}


@contextlib.contextmanager
def dask_client_soon(
    scheduler: str | None = None, workers: int = 2, threads_per_worker: int = 1
) -> Iterator[Future]:
    """:func:`dask_client` started in a background thread, its workers warmed up
    (:func:`warm_worker`): yields a Future of the client, closed on leaving.

    Starting a LocalCluster and importing the detector in its workers takes seconds of
    CPU in other processes; the caller plans the run meanwhile. A run with nothing to do
    pays for a cluster it does not use, which is cheaper than making every run wait.
    """
    from concurrent.futures import ThreadPoolExecutor

    with contextlib.ExitStack() as stack:

        def start() -> Any:
            client = stack.enter_context(dask_client(scheduler, workers, threads_per_worker))
            client.run(warm_worker)
            return client

        # The pool is left first: it waits for a start in progress before the stack closes it.
        with ThreadPoolExecutor(1, thread_name_prefix="streetcd-dask-start") as pool:
            yield pool.submit(start)


def segment_workers(
    client: Any, segment_ids: Sequence[str], sizes: Sequence[int] | None = None
) -> dict[str, str | None]:
    """Assign segments to the workers alive now (each worker's share of the run, see
    :class:`streetcd.dispatch.Dispatcher`), largest first to the least loaded worker, so
    that workers get about the same number of views (``sizes``, default one per segment)
    and finish together."""
    workers = sorted(client.scheduler_info(n_workers=-1)["workers"])
    if not workers:
        return {s: None for s in segment_ids}
    sizes = [1] * len(segment_ids) if sizes is None else list(sizes)
    load = dict.fromkeys(workers, 0)
    out: dict[str, str | None] = {}
    for k in sorted(range(len(segment_ids)), key=lambda k: (-sizes[k], k)):
        worker = min(workers, key=lambda w: (load[w], w))
        out[segment_ids[k]] = worker
        load[worker] += sizes[k]
    return out


def plan_workers(client: Any, plan: Plan) -> dict[str, str | None]:
    """:func:`segment_workers` for the segments of ``plan`` still to do, by views to do."""
    segs = plan.segments_todo
    sizes = {s: 0 for s in segs}
    for b in plan.batches:
        sizes[b.segment_id] += len(b.tasks)
    return segment_workers(client, segs, [sizes[s] for s in segs])


def publish_segment(plan: Plan, finished: Iterable[tuple[Any, Batch]]) -> RunSummary:
    """Publish one segment's batches in the index, each in one transaction as it ends
    (``finished``: (Dask future, batch) pairs, from
    :meth:`streetcd.dispatch.Dispatcher.finished`); a batch lost (its views crashed the
    workers) is logged and counted."""
    summary = RunSummary(plan.run_id)
    with ChangeIndex(plan.index) as idx:
        for future, batch in finished:
            try:
                records = future.result()
            except Exception as exc:  # e.g. KilledWorker: a view that keeps crashing workers
                log.error(
                    "batch %s lost (%s: %s); its %d views stay unpublished and are "
                    "retried by the next run",
                    batch.key,
                    type(exc).__name__,
                    exc,
                    len(batch.tasks),
                )
                summary.n_lost += len(batch.tasks)
                continue
            idx.publish(plan.run_id, records)
            summary.add(records)
            _notify("batch", records)
            future.release()
    return summary


def new_summary(plan: Plan) -> RunSummary:
    """The summary of ``plan`` before any detection: its counts and plan-time failures."""
    return RunSummary(
        plan.run_id,
        n_views=plan.n_views,
        n_skipped=plan.n_skipped,
        n_failed=len(plan.failed_at_plan),
        failures=list(plan.failed_at_plan),
    )


def finish_run(plan: Plan, summary: RunSummary) -> None:
    """Close the run's row in the index with the counts of ``summary`` (from new_summary):
    status ``finished``, or ``incomplete`` when batches were lost."""
    with ChangeIndex(plan.index) as idx:
        idx.finish_run(
            plan.run_id,
            "incomplete" if summary.n_lost else "finished",
            n_planned=plan.n_views,
            n_skipped=plan.n_skipped,
            n_done=summary.n_done,
            n_failed=summary.n_failed,
            n_flagged=summary.n_flagged,
        )


def run_pipeline(
    client: Any,
    images: str | Path,
    poses: str | Path,
    store: str | Path,
    index: str | Path,
    out: str | Path,
    params: PipelineParams = PipelineParams(),
    *,
    retry_failed: bool = False,
) -> RunSummary:
    """One whole run without Prefect: plan, detect every segment on ``client``, publish.

    Holds the index's run lock throughout (:func:`streetcd.index.run_lock`): IndexBusyError
    at once when another run holds it. The steps below it (plan_run, the Dispatcher,
    publish_segment, finish_run) leave locking to their caller.
    """
    from concurrent.futures import ThreadPoolExecutor

    from streetcd.dispatch import Dispatcher

    t0 = time.perf_counter()
    with run_lock(index, "streetcd.pipeline.run_pipeline"):
        plan = plan_run(images, poses, store, index, out, params, retry_failed=retry_failed)
        summary = new_summary(plan)
        segments = plan.segments_todo
        if segments:
            dispatcher = Dispatcher(client, plan).start()
            try:
                with ThreadPoolExecutor(max(1, min(8, len(segments)))) as pool:
                    for part in pool.map(
                        lambda s: publish_segment(plan, dispatcher.finished(s)), segments
                    ):
                        summary.merge(part)
            finally:
                dispatcher.close()
        finish_run(plan, summary)
    summary.wall_s = time.perf_counter() - t0
    return summary
