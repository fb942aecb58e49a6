"""``streetcd report``: a night's review page as a static site, opened offline from a file share.

    DIR/index.html        the page (static/index.html, the same for report and serve)
    DIR/assets/app.js     its script and style, written small, installed with the package:
    DIR/assets/app.css    no CDN, no request leaves the machine
    DIR/data.js           the night's data: ``window.STREETCD = {...}`` (a script, not JSON,
                          because a page opened from ``file://`` may not fetch files)
    DIR/thumbs/*.jpg      per view a change cites: the image, change outlined (``.jpg``), and
                          the old cloud from the same pose (``.old.jpg``), 480 px wide

Full-size images are linked, not copied: a relative path from DIR to the run's image (the
run's inputs as the index recorded them).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import quote

from streetcd.errors import StreetcdError
from streetcd.io.poses import read_poses
from streetcd.report import render
from streetcd.report.changes import (
    class_name,
    load_changes,
    night_numbers,
    pick_run,
    segments,
    view_files,
)
from streetcd.store.crop import crop_for_view, crop_for_views
from streetcd.store.index import ChangeIndex, utc_now
from streetcd.store.records import camera_from_json
from streetcd.store.tiles import TileStore
from streetcd.types import PointCloud, View

STATIC_FILES = ("index.html", "app.js", "app.css")
RENDER_THREADS = 4  # OpenCV and the tile reads let go of the GIL; 4 keeps 2 cores busy
CROP_BATCH = 8  # neighbouring views cropped together
MAX_RANGE_M = 60.0  # the old cloud is drawn to this range (the detector default)


@dataclass
class Sources:
    """Where a view's pictures come from. A view is known by its key in the index (an image
    name, or ``name#hash``); its image and camera are looked up in the index first (schema
    4 keeps both), then in the run's images folder and pose file. ``store`` is the run's tile
    store; ``notes`` says, once each, what is missing (the page then shows less)."""

    images: Path | None = None
    poses: dict[str, View] = field(default_factory=dict)
    paths: dict[str, Path] = field(default_factory=dict)
    cameras: dict[str, View] = field(default_factory=dict)
    store: TileStore | None = None
    notes: list[str] = field(default_factory=list)

    def image_of(self, key: str, given: str | None = None) -> Path | None:
        """The image file of view ``key`` (``given``: the path the change object names)."""
        for candidate in (given, self.paths.get(key)):
            if candidate and Path(candidate).is_file():
                return Path(candidate)
        if self.images is not None and (self.images / image_name(key)).is_file():
            return self.images / image_name(key)
        return None

    def view_of(self, key: str) -> View | None:
        """The camera of view ``key`` (pose in the CRS), or None."""
        name = image_name(key)
        return self.cameras.get(key) or self.poses.get(name) or self.poses.get(Path(name).stem)


def image_name(key: str) -> str:
    """The image's file name in a view key (``IMG_0001.jpg#3f2a…`` → ``IMG_0001.jpg``)."""
    return key.split("#", 1)[0]


def open_sources(run: dict[str, Any] | None, index_path: Path, keys: list[str]) -> Sources:
    """The pictures' sources for the views ``keys``: what the index records of them and the
    run's inputs (``runs.config``: images, poses, store), opened; what is missing or
    unreadable becomes a note, never an error."""
    src = Sources()
    with ChangeIndex(index_path, create=False) as idx:
        for key, path, camera in view_files(idx, keys):
            if path:
                src.paths[key] = Path(path)
            if camera:
                src.cameras[key] = camera_from_json(key, camera)
    inputs = (run or {}).get("inputs") or {}
    if inputs.get("images") and Path(inputs["images"]).is_dir():
        src.images = Path(inputs["images"])
    elif len(src.paths) < len(keys):
        src.notes.append(f"images folder not found ({inputs.get('images')}): fewer thumbnails")
    if len(src.cameras) < len(keys) and inputs.get("poses"):
        try:
            poses = read_poses(inputs["poses"], src.images)
            src.poses = {v.name: v for v in poses.views} | {v.stem: v for v in poses.views}
        except (StreetcdError, OSError) as exc:
            src.notes.append(f"poses not read ({exc}): fewer old-cloud pictures and boxes")
    try:
        src.store = TileStore.open(inputs["store"]) if inputs.get("store") else None
    except (StreetcdError, OSError) as exc:
        src.notes.append(f"tile store not opened ({exc}): no old-cloud pictures")
    if src.store is None and not any("tile store" in n for n in src.notes):
        src.notes.append("the run names no tile store: no old-cloud pictures")
    return src


def safe_name(view: str) -> str:
    """A file name for ``view``'s thumbnails: its stem in plain characters and a short hash
    of the full name, so names that differ only in odd characters never collide."""
    stem = re.sub(r"[^A-Za-z0-9._-]", "_", Path(view).stem)[:80]
    return f"{stem}-{hashlib.sha1(view.encode('utf-8')).hexdigest()[:8]}"


def render_view(
    name: str,
    entry: dict[str, Any],
    src: Sources,
    out: Path,
    cloud: PointCloud | None = None,
    max_range_m: float = MAX_RANGE_M,
) -> dict[str, Any]:
    """Write ``thumbs/<safe>.jpg`` (image, change outlined) and ``thumbs/<safe>.old.jpg``
    (old cloud, same pose) for view ``name``; return ``{thumb, old, size, image, note}``
    with paths relative to ``out`` (None where a picture could not be made, and why).
    ``cloud``: the old cloud around the view, already cropped (else cropped here)."""
    media: dict[str, Any] = {"thumb": None, "old": None, "size": None, "image": None, "note": None}
    image_path = src.image_of(name, entry.get("image_path"))
    if image_path is None:
        media["note"] = "image not found"
        return media
    media["image"] = image_path
    stem = safe_name(name)
    try:
        picture = render.read_thumbnail(image_path)
    except StreetcdError as exc:
        media["note"] = str(exc)
        return media
    mask = render.read_mask(entry["mask"]) if entry.get("mask") else None
    if mask is not None:
        picture = render.outline(picture, mask)
    h, w = picture.shape[:2]
    media["size"] = [w, h]
    (out / "thumbs" / f"{stem}.jpg").write_bytes(render.encode_jpeg(picture))
    media["thumb"] = f"thumbs/{stem}.jpg"
    view = src.view_of(name)
    if view is None or src.store is None:
        media["note"] = "no pose" if view is None else "no tile store"
        return media
    try:
        if cloud is None:
            cloud = crop_for_view(src.store, view, max_range_m=max_range_m)
        old = render.splat_cloud(cloud, view, (w, h), max_range_m)
    except StreetcdError as exc:  # one view's damaged tile costs its picture, not the page
        media["note"] = f"old cloud not rendered: {exc}"
        return media
    (out / "thumbs" / f"{stem}.old.jpg").write_bytes(render.encode_jpeg(old))
    media["old"] = f"thumbs/{stem}.old.jpg"
    return media


def render_batch(
    batch: list[tuple[str, dict[str, Any]]], src: Sources, out: Path
) -> list[dict[str, Any]]:
    """:func:`render_view` for a few neighbouring views, with one crop of the old cloud for
    them all (a crop is most of a picture's cost; neighbours share most of their tiles)."""
    cloud = None
    cameras = [v for v in (src.view_of(name) for name, _ in batch) if v is not None]
    if src.store is not None and cameras:
        try:
            cloud = crop_for_views(src.store, cameras, max_range_m=MAX_RANGE_M)
        except StreetcdError:
            cloud = None  # each view then crops on its own and notes its own error
    return [render_view(name, entry, src, out, cloud) for name, entry in batch]


def relative_link(target: Path, out: Path) -> str:
    """``target`` as a URL relative to the folder ``out`` (works from a file share)."""
    rel = os.path.relpath(Path(target).resolve(), Path(out).resolve())
    return quote(Path(rel).as_posix())


def render_all(
    changes: list[dict[str, Any]], src: Sources, out: Path, threads: int = RENDER_THREADS
) -> dict[str, dict[str, Any]]:
    """:func:`render_view` once per view that any change cites, in batches of
    :data:`CROP_BATCH` views of one segment (in key order: along the street), ``threads``
    batches at a time; ``{view: media}``."""
    entries: dict[str, dict[str, Any]] = {}
    segment_of: dict[str, str] = {}
    for change in changes:
        for v in change.get("views") or ():
            entries.setdefault(v["view"], v)
            segment_of.setdefault(v["view"], str(change.get("segment")))
    order = sorted(entries, key=lambda k: (segment_of[k], k))
    batches = [
        [(k, entries[k]) for k in order[i : i + CROP_BATCH]]
        for i in range(0, len(order), CROP_BATCH)
    ]
    (out / "thumbs").mkdir(parents=True, exist_ok=True)
    media: dict[str, dict[str, Any]] = {}
    with ThreadPoolExecutor(max(1, threads)) as pool:
        done = pool.map(lambda b: render_batch(b, src, out), batches)
        for batch, results in zip(batches, done, strict=True):
            media.update(zip((k for k, _ in batch), results, strict=True))
    return {k: media[k] for k in entries}


def page_data(
    index_path: Path,
    changes: list[dict[str, Any]],
    media: dict[str, dict[str, Any]],
    src: Sources,
    full_link: Callable[[str, Path], str],
    *,
    run_id: str | None = None,
    live: bool = False,
) -> dict[str, Any]:
    """The data of the page (``window.STREETCD``): ``numbers``, ``segments``, ``changes`` best
    first, each with its views' pictures and where the change lies in each (``box``: [left,
    top, right, bottom] fractions of the image), and the CRS. ``full_link(view, path)`` is
    the URL of a view's full-size image."""
    with ChangeIndex(index_path, create=False) as idx:
        run = pick_run(idx, run_id)
        data: dict[str, Any] = {
            "title": f"streetcd review: {index_path.name}",
            "generated_at": utc_now(),
            "crs": idx.crs,
            "live": live,
            "numbers": night_numbers(idx, run),
            "segments": segments(idx),
            "notes": list(src.notes),
        }
    out_changes = []
    for c in changes:
        views = []
        for v in c.get("views") or ():
            m = media.get(v["view"], {})
            view = src.view_of(v["view"])
            box = (
                render.project_box(c["bbox"], view) if view is not None and c.get("bbox") else None
            )
            views.append(
                {
                    "view": v["view"],
                    "sees_change": bool(v.get("sees_change", True)),
                    "thumb": m.get("thumb"),
                    "old": m.get("old"),
                    "size": m.get("size"),
                    "full": full_link(v["view"], m["image"]) if m.get("image") else None,
                    "box": box,
                    "note": m.get("note"),
                }
            )
        out_changes.append(
            {
                "id": str(c["id"]),
                "kind": c.get("kind", "unknown"),
                "class": int(c["class"]),
                "class_name": class_name(c["class"]),
                "confidence": round(float(c["confidence"]), 4),
                "centroid": [round(float(x), 3) for x in c.get("centroid") or ()],
                "bbox": [round(float(x), 3) for x in c.get("bbox") or ()],
                "segment": c.get("segment"),
                "first_seen": c.get("first_seen"),
                "last_seen": c.get("last_seen"),
                "review": c.get("review"),
                "transient": c.get("transient") or None,  # why it is not a street change
                "views": views,
            }
        )
    data["changes"] = out_changes
    return data


def data_script(data: dict[str, Any]) -> bytes:
    """``data`` as the script ``data.js``. ``<`` is escaped so no text in it can end a script."""
    text = json.dumps(data, separators=(",", ":"), allow_nan=False).replace("<", "\\u003c")
    return f"window.STREETCD = {text};\n".encode()


def copy_static(out: Path) -> None:
    """``index.html`` into ``out`` and the script and style into ``out/assets``."""
    static = resources.files("streetcd.report") / "static"
    (out / "assets").mkdir(parents=True, exist_ok=True)
    for name in STATIC_FILES:
        target = out / name if name == "index.html" else out / "assets" / name
        with resources.as_file(static / name) as path:
            shutil.copyfile(path, target)


@dataclass(frozen=True)
class ReportResult:
    """What :func:`write_report` made: the page, how many changes and views it shows, how
    many pictures it drew, the seconds it took, and notes on what it could not show."""

    page: Path
    changes: int
    views: int
    pictures: int
    seconds: float
    notes: tuple[str, ...]


@dataclass
class Site:
    """A written site and what a live server needs to refresh its data: the pictures by view
    (:func:`render_view`'s media) and the run's opened sources."""

    result: ReportResult
    media: dict[str, dict[str, Any]]
    sources: Sources


def build_site(
    index_path: str | Path,
    out: str | Path,
    *,
    run_id: str | None = None,
    threads: int = RENDER_THREADS,
    full_link: Callable[[str, Path], str] | None = None,
    live: bool = False,
) -> Site:
    """Write the review site of ``index_path`` into the folder ``out`` (made if needed;
    files of an earlier report there are replaced). ``run_id`` picks the run whose numbers
    and inputs the page uses (default: the latest). ``full_link(view, path)`` is the URL of
    a full-size image (default: relative to ``out``)."""
    t0 = time.perf_counter()
    index_path, out = Path(index_path), Path(out)
    with ChangeIndex(index_path, create=False) as idx:
        run = pick_run(idx, run_id)
    changes = load_changes(index_path)
    keys = sorted({v["view"] for c in changes for v in c.get("views") or ()})
    src = open_sources(run, index_path, keys)
    out.mkdir(parents=True, exist_ok=True)
    media = render_all(changes, src, out, threads)
    link = full_link or (lambda _v, p: relative_link(p, out))
    data = page_data(index_path, changes, media, src, link, run_id=run_id, live=live)
    (out / "data.js").write_bytes(data_script(data))
    copy_static(out)
    pictures = sum((m["thumb"] is not None) + (m["old"] is not None) for m in media.values())
    result = ReportResult(
        out / "index.html",
        len(changes),
        len(media),
        pictures,
        time.perf_counter() - t0,
        tuple(src.notes),
    )
    return Site(result, media, src)


def write_report(
    index_path: str | Path,
    out: str | Path,
    *,
    run_id: str | None = None,
    threads: int = RENDER_THREADS,
) -> ReportResult:
    """``streetcd report``: :func:`build_site` for a static site; what it made."""
    return build_site(index_path, out, run_id=run_id, threads=threads).result
