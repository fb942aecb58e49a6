"""Planning a night: which views to detect, in which segments and batches.

:func:`plan_run` reads the poses, the images folder, the tile store's index and the change
index, and writes nothing: it cuts the views into street segments, hashes every view's
inputs and leaves out the views the index already holds with the same input and results
hashes. What it finds wrong with single views (an image without a pose, a pose without an
image, a bad pose row) becomes failed records in the plan, for the publisher to record
(:func:`streetcd.run.publish.register_plan`).
"""

from __future__ import annotations

import hashlib
import json
import os
import time
import uuid
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import cached_property
from pathlib import Path

import numpy as np

from streetcd.config import Config
from streetcd.errors import CRSMismatchError
from streetcd.io.images import list_images
from streetcd.io.las import crs_string
from streetcd.io.poses import read_poses
from streetcd.run.segments import Segment, plan_segments
from streetcd.store.index import ChangeIndex
from streetcd.store.records import ViewRecord
from streetcd.store.tiles import TileStore
from streetcd.types import PoseSet, View


@dataclass(frozen=True)
class ViewTask:
    """One view's work: the view (pose in the CRS, image path), its neighbours, its hash,
    and its lasting key in the index (:func:`lasting_key`; the name when not given)."""

    view: View
    neighbours: tuple[View, ...]
    segment_id: str
    input_hash: str
    key: str = ""


@dataclass(frozen=True)
class Batch:
    """Consecutive views of one segment, processed by one Dask task.

    crop_views : the views whose clouds the segment's batches share: every view of the
        segment, done or not, and its neighbours (a view's result depends on its crop:
        :func:`_batches`). All batches of a segment carry the same tuple, so a worker crops
        the segment once and serves its later batches, and the detector's surface cache,
        from that one cloud (:class:`streetcd.run.worker.WorkerRuntime`); empty: the batch's
        own views and their neighbours (:func:`streetcd.run.worker.batch_views`).
    store_generation : the tile store's generation at planning, so a long-lived worker
        never reads a store it opened before the last ingest.
    store_id : :func:`store_identity` of the tile store at planning (a store rebuilt at the
        same path starts its generations again; this tells it apart), for the workers' caches.
    part : set on the single-view batches a batch was cut into (the end of a worker's
        queue, :func:`streetcd.run.dispatch.split_tail`): the view's position in the batch.
    """

    segment_id: str
    number: int
    tasks: tuple[ViewTask, ...]
    store: str
    out_dir: str
    config: Config
    params_hash: str
    crop_views: tuple[View, ...] = ()
    store_generation: int | None = None
    part: int | None = None
    store_id: str | None = None

    @property
    def key(self) -> str:
        tail = "" if self.part is None else f".{self.part}"
        return f"detect-{self.segment_id}-{self.number}{tail}"


@dataclass(frozen=True)
class Plan:
    """What a run will do. ``batches`` hold only the views still to process;
    ``failed_at_plan`` the records of views that failed before any detection and are new to
    the index; ``inputs`` the run's folders and files, as the index records them."""

    run_id: str
    index: str
    crs: str | None
    segments: tuple[Segment, ...]
    batches: tuple[Batch, ...]
    n_views: int
    n_skipped: int
    failed_at_plan: tuple[ViewRecord, ...]
    params_hash: str
    inputs: tuple[tuple[str, str], ...] = ()

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


def file_hash(path: Path, chunk: int = 1 << 20) -> str:
    """SHA-256 (16 hex digits) of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while block := fh.read(chunk):
            h.update(block)
    return h.hexdigest()[:16]


def store_identity(store: TileStore) -> str:
    """Hash of the store's committed root record: its settings, generation and every source
    file's key (path, size, mtime), so it changes with any ingest and tells apart two stores
    built one after the other at the same path."""
    return hash_text(json.dumps(store.index, sort_keys=True, default=str))


def tiles_fingerprint(
    store: TileStore,
    center: np.ndarray,
    radius_m: float,
    memo: dict[str, str] | None = None,
) -> str:
    """Hash of the tiles (id, fragments, counts) within ``radius_m`` of ``center`` (CRS).

    The view's cloud is cropped from a subset of these (the frustum is range-limited), so
    ingesting a new MLS file changes the hash of exactly the views it can affect. ``memo``
    ({tile id: its text}) keeps each tile's text for the next view: neighbouring views share
    most of their tiles.
    """
    c = np.asarray(center, dtype=np.float64)
    tiles = store.tiles_in_bbox(c[0] - radius_m, c[1] - radius_m, c[0] + radius_m, c[1] + radius_m)
    memo = {} if memo is None else memo
    parts = []
    for t in tiles:
        text = memo.get(t.id)
        if text is None:
            text = memo[t.id] = f"{t.id}:" + ",".join(f"{f.key}/{f.count}" for f in t.fragments)
        parts.append(text)
    return hash_text(";".join(sorted(parts)))


@dataclass(frozen=True)
class NightListing:
    """What a night's images folder and pose file hold, read once (:func:`list_night`) and
    shared by the input check and the plan: reading a city's pose file and resolving every
    image path twice cost ~4 s of a 10,000-view night (docs/BENCHMARKS.md).

    images, poses : the resolved paths it was read from. files, refused : as
    :func:`readable_images` returns them. pose_set : the pose file's views (``read_poses``),
    bad_rows : its rows that failed, (name, why).
    """

    images: Path
    poses: Path
    files: dict[str, Path]
    refused: dict[str, tuple[str, Path | None]]
    pose_set: PoseSet
    bad_rows: list[tuple[str, str]]


def list_night(images: str | Path, poses: str | Path) -> NightListing:
    """:class:`NightListing` of ``images`` and ``poses`` (paths resolved: workers run
    elsewhere, another cwd or machine with the same mounts)."""
    images, poses = Path(images).resolve(), Path(poses).resolve()
    files, refused = readable_images(list_images(images), images)
    bad_rows: list[tuple[str, str]] = []
    pose_set = read_poses(poses, image_dir=images, bad_rows=bad_rows)
    return NightListing(images, poses, files, refused, pose_set, bad_rows)


def plan_run(
    images: str | Path,
    poses: str | Path,
    store: str | Path,
    index: str | Path,
    out: str | Path,
    config: Config = Config(),
    *,
    retry_failed: bool = False,
    run_id: str | None = None,
    listing: NightListing | None = None,
) -> Plan:
    """Plan a run; reads, writes nothing (see the module docstring).

    images : folder of the new images. poses : a pose file (COLMAP or OPK CSV) naming them.
    store : the tile store of the reference cloud. index : the change index (need not exist
    yet). out : where masks and overlays go. A view is skipped when the index holds it with
    the same input and results hashes (``done``, or ``failed`` unless ``retry_failed``).
    listing : the folder and pose file as already read (:func:`list_night`, the input
    check's), or None to read them here.
    """
    run_id = run_id or time.strftime("%Y%m%dT%H%M%S") + "-" + uuid.uuid4().hex[:6]
    # Workers run elsewhere (another cwd, another machine with the same mounts): absolute paths.
    images, poses, store, out = (Path(p).resolve() for p in (images, poses, store, out))
    if listing is None or (listing.images, listing.poses) != (images, poses):
        listing = list_night(images, poses)
    files, refused = listing.files, listing.refused
    bad_rows, pose_set = listing.bad_rows, listing.pose_set
    tile_store = TileStore.open(store)
    crs = crs_string(pose_set.crs) if pose_set.crs else None
    store_crs = crs_string(tile_store.crs) if tile_store.crs else None
    if crs and store_crs and crs != store_crs:
        raise CRSMismatchError(f"poses {poses} are in {crs}, tile store {store} in {store_crs}")
    crs = crs or store_crs
    phash = config.results_hash()
    views, failed = _match_images(pose_set.views, bad_rows, files, images, poses, phash, refused)
    segments = plan_segments(
        views,
        config.run.segments,
        config.detect.correlate.n_neighbours,
        min_parallax_px=config.detect.correlate.min_parallax_px,
    )
    known = _known_views(Path(index))

    def skip(name: str, input_hash: str) -> bool:
        have = known.get(name)
        return (
            have is not None
            and have[:2] == (input_hash, phash)
            and (have[2] == "done" or not retry_failed)
        )

    tasks, n_skipped = _view_tasks(segments, views, tile_store, config, skip)
    batches = _batches(segments, tasks, views, config, str(store), str(out), phash, tile_store)
    new_failed = tuple(r for r in failed if not skip(r.view, r.input_hash))
    n_skipped += len(failed) - len(new_failed)
    inputs = {"images": str(images), "poses": str(poses), "store": str(store), "out": str(out)}
    return Plan(
        run_id,
        str(index),
        crs,
        tuple(segments),
        tuple(batches),
        len(views) + len(failed),
        n_skipped,
        new_failed,
        phash,
        tuple(inputs.items()),
    )


def _known_views(index: Path) -> dict[str, tuple[str, str, str]]:
    """:meth:`ChangeIndex.processed` of ``index``, empty when it does not exist yet."""
    if not index.exists():
        return {}
    with ChangeIndex(index, create=False) as idx:
        return idx.processed()


def _match_images(
    posed: Sequence[View],
    bad_rows: Sequence[tuple[str, str]],
    files: dict[str, Path],
    images: Path,
    poses: Path,
    phash: str,
    refused: dict[str, tuple[str, Path | None]] | None = None,
) -> tuple[list[View], list[ViewRecord]]:
    """The views with a pose and an image, and a failed record for every image or pose
    without its other half, every malformed pose row, every view posed twice and every image
    that is ``refused`` ({name: (why, path to hash or None)}, :func:`readable_images`).

    A pose names its image by its file name in ``images`` exactly: the view's image is that
    listed file, never a path built from the name (a name is checked by the pose reader,
    :func:`streetcd.io.poses.image_name_problem`, but matching only listed files is what keeps
    every read inside ``images``)."""
    refused = refused or {}
    posed_twice = _posed_twice([v.name for v in posed] + [n for n, _ in bad_rows])
    failed = _bad_pose_records(bad_rows, posed_twice, files, phash, poses)
    failed += [
        ViewRecord(
            lasting_key(name, _file_hash_or(files.get(name), None), poses),
            hash_text(
                f"{name}|posed {n} times|" + (_file_hash_or(files.get(name), None) or "missing")
            ),
            phash,
            None,
            "failed",
            f"InputError: {poses}: view {name!r} has {n} poses; keep one",
        )
        for name, n in posed_twice.items()
    ]
    views: list[View] = []
    for v in posed:
        if v.name in posed_twice:
            continue
        if v.name in files:
            views.append(replace(v, image=files[v.name]))
        else:
            why = refused[v.name][0] if v.name in refused else None
            failed.append(
                ViewRecord(
                    lasting_key(v.name, None, poses),
                    hash_text(view_key(v, "missing") + (why or "")),
                    phash,
                    None,
                    "failed",
                    f"InputError: {why}" if why else f"image not found: {Path(images) / v.name}",
                    center=xyz(v.center),
                )
            )
    have_pose = {v.name for v in views}
    have_pose |= {image_name(r.view) for r in failed}  # a bad or repeated row failed its image
    for name, path in files.items():
        if name not in have_pose:
            content = file_hash(path)
            failed.append(
                ViewRecord(
                    lasting_key(name, content),
                    content,
                    phash,
                    None,
                    "failed",
                    f"no pose for image {name} in {poses}",
                )
            )
    for name, (why, readable) in refused.items():
        if name not in have_pose:
            bytes_hash = _file_hash_or(readable, None)
            failed.append(
                ViewRecord(
                    lasting_key(name, bytes_hash, poses),
                    hash_text(f"{name}|{why}|{bytes_hash}"),
                    phash,
                    None,
                    "failed",
                    f"InputError: {why}",
                )
            )
    return views, failed


def readable_images(
    files: dict[str, Path], images: Path
) -> tuple[dict[str, Path], dict[str, tuple[str, Path | None]]]:
    """Split the listed images of the folder ``images`` into those a run may read and
    {shown name: (why not, the file to hash or None)} for the others: a link that resolves
    outside ``images`` (never read, not even hashed) and a name that is not UTF-8 (the index
    and the logs hold text; shown with ``\\xNN`` escapes). Each fails its own view only."""
    images = images.resolve()
    keep: dict[str, Path] = {}
    refused: dict[str, tuple[str, Path | None]] = {}
    for name, path in files.items():
        shown = os.fsencode(name).decode("utf-8", "backslashreplace")
        try:
            # a file that is no link, directly in the resolved folder, is where it is: one
            # lstat, not realpath's walk up every folder of its path
            direct = path.parent == images and not os.path.islink(path)
            target = path if direct else path.resolve(strict=True)
        except (OSError, RuntimeError) as exc:  # a dangling link, a loop of links
            refused[shown] = (f"{images / shown}: cannot be resolved: {exc}", None)
            continue
        if not target.is_relative_to(images):
            refused[shown] = (f"{images / shown}: is a link to a file outside {images}", None)
        elif shown != name:
            refused[shown] = (f"{images / shown}: file name is not UTF-8; rename the file", path)
        else:
            keep[name] = path
    return keep, refused


def _view_tasks(
    segments: Sequence[Segment],
    views: Sequence[View],
    store: TileStore,
    config: Config,
    skip: Callable[[str, str], bool],
) -> tuple[dict[str, list[ViewTask]], int]:
    """{segment id: its views still to do}, and how many were skipped: a view's input hash
    covers its image, pose and camera, the tiles around it and its neighbours'."""
    image_hash = {v.name: file_hash(v.image) for v in views if v.image is not None}
    by_name = {v.name: v for v in views}
    # once a view, not once more for each view that has it as a neighbour
    keys = {v.name: view_key(v, image_hash[v.name]) for v in views}
    reach_m = config.detect.max_range_m + 2.0  # crop buffer (1 m) and some slack
    out: dict[str, list[ViewTask]] = {}
    n_skipped = 0
    tile_texts: dict[str, str] = {}  # tiles_fingerprint's memo
    for seg in segments:
        todo = out.setdefault(seg.id, [])
        for name, nbrs in zip(seg.views, seg.neighbours, strict=True):
            v = by_name[name]
            parts = [keys[name], tiles_fingerprint(store, v.center, reach_m, tile_texts)]
            parts += [keys[n] for n in nbrs]
            h = hash_text("\n".join(parts))
            key = lasting_key(name, image_hash[name])
            if skip(key, h):
                n_skipped += 1
            else:
                todo.append(ViewTask(v, tuple(by_name[n] for n in nbrs), seg.id, h, key))
    return out, n_skipped


def _batches(
    segments: Sequence[Segment],
    tasks: dict[str, list[ViewTask]],
    views: Sequence[View],
    config: Config,
    store: str,
    out: str,
    phash: str,
    tile_store: TileStore,
) -> list[Batch]:
    """Each segment's views to do cut into batches of ``run.batch_size``, in trajectory order,
    each with the segment's crop views: all its views and their neighbours, done or not.

    Why all of them: the detector estimates the cloud's point spacing from the crop it is
    given (:mod:`streetcd.detect.spacing`), so a view's result depends on the crop's extent. A
    night resumed after a kill, or run again with some views done, crops each segment as a
    clean night does and gives its views the same results (docs/DECISIONS.md, "The crop a
    view is detected on")."""
    size = config.run.batch_size
    by_name = {v.name: v for v in views}
    generation = tile_store.index.get("generation")
    identity = store_identity(tile_store)
    batches = []
    for seg in segments:
        todo = tasks[seg.id]
        names = set(seg.views).union(*seg.neighbours)
        shared = tuple(by_name[n] for n in sorted(names))
        for k in range(0, len(todo), size):
            chunk = tuple(todo[k : k + size])
            batches.append(
                Batch(
                    seg.id,
                    k // size,
                    chunk,
                    store,
                    out,
                    config,
                    phash,
                    shared,
                    generation,
                    store_id=identity,
                )
            )
    return batches


def _bad_pose_records(
    bad_rows: Sequence[tuple[str, str]],
    posed_twice: dict[str, int],
    files: dict[str, Path],
    phash: str,
    poses: Path | None = None,
) -> list[ViewRecord]:
    """A failed record for each malformed pose row (its error names the file, line and
    field). Its input hash covers the error and the image, so fixing the row, or the image,
    makes the view due again. A name with more than one row fails as a repeat instead."""
    out = []
    for name, error in bad_rows:
        if name in posed_twice:
            continue
        content = _file_hash_or(files.get(name), None)
        key = f"{name}|{error}|{content or 'missing'}"
        out.append(
            ViewRecord(
                lasting_key(name, content, poses),
                hash_text(key),
                phash,
                None,
                "failed",
                f"InputError: {error}",
            )
        )
    return out


def _posed_twice(names: Sequence[str]) -> dict[str, int]:
    """{name: count} of the view names with more than one pose row (good or bad): which
    pose is meant cannot be known, so such a view fails (rather than the whole run)."""
    counts: dict[str, int] = {}
    for name in names:
        counts[name] = counts.get(name, 0) + 1
    return {name: n for name, n in counts.items() if n > 1}


def view_key(view: View, image_hash: str) -> str:
    """The text a view's input hash covers: name, image, pose and camera."""
    i = view.intrinsics
    pose = np.concatenate([view.pose.R.ravel(), view.pose.t]).round(9)
    return (
        f"{view.name}|{image_hash}|{pose.tolist()}|{i.width},{i.height},{i.fx!r},{i.fy!r},"
        f"{i.cx!r},{i.cy!r},{list(i.dist)}"
    )


def _file_hash_or(path: Path | None, default: str | None) -> str | None:
    return file_hash(path) if path is not None else default


def lasting_key(name: str, content_hash: str | None, poses: Path | None = None) -> str:
    """A view's key in the change index, unique across nights and archives:
    ``<image name>#<12 hex digits of the image's SHA-256>``. Cameras reuse names every
    night; the bytes of two different photographs never agree, and the same photograph
    planned twice (a rerun, a moved archive) keeps its key, so its result is kept, not
    redone. A view without an image file (a pose whose image is missing) is keyed by the
    pose file instead: ``<name>#pose-<12 hex digits of the pose file's path>``."""
    if content_hash is not None:
        return f"{name}#{content_hash[:12]}"
    return f"{name}#pose-{hash_text(str(poses))[:12]}"


def image_name(key: str) -> str:
    """The image name of a lasting key (:func:`lasting_key`); a bare name is its own."""
    return key.rsplit("#", 1)[0]


def xyz(a: np.ndarray) -> tuple[float, float, float]:
    """A (3,) array as a tuple of floats (the index's columns)."""
    return float(a[0]), float(a[1]), float(a[2])


def hash_text(text: str) -> str:
    """SHA-256 (16 hex digits) of ``text``."""
    return hashlib.sha256(text.encode()).hexdigest()[:16]
