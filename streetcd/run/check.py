"""Checking a night's inputs before anything starts: ``streetcd check``, and the first step
of every ``streetcd run`` (before the Prefect server and the Dask cluster).

:func:`check_inputs` reads what is cheap to read — the images folder, the image *headers*
(no pixel is decoded), the pose file, the tile store's index and the change index's CRS —
and sorts what it finds three ways:

- **whole-input errors** are raised, one line that names the file and the field: a missing
  or empty images folder, pose file or store, a busy index, CRSs that disagree, poses that
  lie nowhere near the store (a local frame), or inputs where not a single view could
  succeed. Nothing runs then (``streetcd run`` exits 2).
- **warnings**: views that will fail alone, recorded as failed by the run (an image without
  a pose and the reverse, an image of another size than its camera, a header beyond the
  pixel limit, a camera with no reference points in reach).
- **notes**: what the run adapts to and says so (images of the poses' cameras at another
  resolution: their intrinsics are rescaled), and what the store holds near the views (class
  codes).
"""

from __future__ import annotations

import math
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

from streetcd.config import Config, DetectParams
from streetcd.errors import CRSMismatchError, InputError, MissingInputError, StreetcdError
from streetcd.store.locks import lock_path, run_lock

if TYPE_CHECKING:
    from streetcd.run.plan import NightListing
    from streetcd.store.tiles import TileStore
    from streetcd.types import View

NAMES_SHOWN = 3  # example names in a warning about many views


@dataclass(frozen=True)
class CheckReport:
    """What :func:`check_inputs` found, short of a whole-input error.

    image_names, pose_names : the image files in the folder and the view names in the pose
    file. crs : the CRS the night will be in (None: a local frame). notes, warnings : one
    line each (see the module docstring). seconds : how long the check took. listing :
    the folder and pose file as read (the run plans from it, not reading them again).
    """

    image_names: frozenset[str]
    pose_names: frozenset[str]
    crs: str | None
    notes: tuple[str, ...]
    warnings: tuple[str, ...]
    seconds: float
    listing: NightListing | None = field(default=None, compare=False, repr=False)


def check_inputs(
    images: str | Path,
    poses: str | Path,
    store: str | Path,
    index: str | Path | None = None,
    config: Config = Config(),
    *,
    check_lock: bool = True,
    archive: str | Path | None = None,
) -> CheckReport:
    """Check a night's inputs (see the module docstring); writes nothing.

    images : the images folder. poses : the pose file. store : the tile store. index : the
    change index (need not exist). check_lock : whether a busy index is an error (the run
    itself, which holds the lock, passes False). archive : the LAS/LAZ folder the run will
    ingest first: a store that does not exist yet is then not an error, and what needs its
    tiles is left to the run's own check after the ingest.
    """
    t0 = time.perf_counter()
    images, poses, store = Path(images), Path(poses), Path(store)
    _exist(images, poses, store, archive)
    if index is not None and check_lock and lock_path(index).exists():
        with run_lock(index, "streetcd check"):  # IndexBusyError naming the holder
            pass
    # imported now, not with the module: a missing input answers before a second of imports
    from streetcd.run.plan import list_night

    # links out of the folder and non-UTF-8 names are never read; each fails its own view
    listing = list_night(images, poses)
    files, refused = listing.files, listing.refused
    if not files and not refused:
        raise InputError(f"{images}: no images (.jpg, .jpeg, .png, .tif, .tiff) in this folder")
    notes: list[str] = []
    warnings: list[str] = []
    if refused:
        first = next(iter(refused.values()))[0]
        warnings.append(f"{len(refused)} image(s) will fail unread: {_some(refused)}; e.g. {first}")
    bad_rows, pose_set = listing.bad_rows, listing.pose_set
    if not pose_set.views:
        first = f"; first bad row: {bad_rows[0][1]}" if bad_rows else ""
        raise InputError(f"{poses}: no usable pose ({len(bad_rows)} bad row(s){first})")
    if archive is not None and not store.exists():
        tiles = None
        notes.append(f"tile store {store} will be made from {archive}; checked after the ingest")
    else:
        tiles = _open_store(store)
    crs = _agreed_crs(poses, pose_set.crs, store, tiles.crs if tiles else None, index)
    posed = {v.name: v for v in pose_set.views}
    warnings += _unmatched(files, posed, poses, images)
    both = [posed[n] for n in sorted(posed) if n in files]
    if not both:
        raise InputError(
            f"{poses}: none of its {len(posed)} view names is an image in {images} "
            f"(poses name e.g. {_some(posed)}; the folder holds e.g. {_some(files)})"
        )
    reach_m = config.detect.max_range_m
    near = _near_store(both, tiles, reach_m) if tiles is not None else {v.name: v for v in both}
    if not near and tiles is not None:
        raise InputError(
            f"{poses}: no camera centre lies within {reach_m:g} m (detect.max_range_m) of the "
            f"tile store {store} (cameras x {_span(both, 0)}, y {_span(both, 1)}; store x "
            f"{_store_span(tiles, 0)}, y {_store_span(tiles, 1)}): poses in another frame or CRS?"
        )
    far = [v.name for v in both if v.name not in near]
    if far:
        warnings.append(
            f"{len(far)} view(s) have no reference point within {reach_m:g} m and will fail: "
            f"{_some(far)}"
        )
    size_notes, failing, first_error = _image_sizes(both, files, config.run.max_image_pixels)
    notes += size_notes
    if len(failing) == len(both):
        raise InputError(f"{first_error} (and so every one of the {len(both)} images)")
    if failing:
        warnings.append(f"{len(failing)} view(s) will fail: {_some(failing)}; e.g. {first_error}")
    if tiles is not None:
        views = [near[n] for n in sorted(near)]
        notes += _class_codes(tiles, views, reach_m, warnings, config.detect)
    return CheckReport(
        frozenset(files) | frozenset(refused),
        frozenset(posed) | {name for name, _ in bad_rows},
        crs,
        tuple(notes),
        tuple(warnings),
        time.perf_counter() - t0,
        listing,
    )


def _exist(images: Path, poses: Path, store: Path, archive: str | Path | None) -> None:
    """MissingInputError naming the first input that is not there."""
    if not images.is_dir():
        raise MissingInputError(f"images folder not found: {images}")
    if not poses.exists():
        raise MissingInputError(f"pose file not found: {poses}")
    if archive is None and not store.exists():
        raise MissingInputError(f"tile store not found: {store}")


def _open_store(store: Path) -> TileStore:
    from streetcd.store.tiles import TileStore

    if not store.exists():
        raise MissingInputError(f"tile store not found: {store}")
    tiles = TileStore.open(store)
    if len(tiles) == 0:
        raise InputError(f"{store}: the tile store holds no tiles (ingest an archive first)")
    return tiles


def _agreed_crs(
    poses: Path,
    poses_crs: object | None,
    store: Path,
    store_crs: str | None,
    index: str | Path | None,
) -> str | None:
    """The one CRS of poses, store and index (each may state none); CRSMismatchError naming
    the files when two disagree."""
    from streetcd.io.las import crs_string
    from streetcd.store.index import ChangeIndex

    stated: list[tuple[str, str]] = []
    if poses_crs:
        stated.append((f"poses {poses}", crs_string(poses_crs)))
    if store_crs:
        stated.append((f"tile store {store}", crs_string(store_crs)))
    if index is not None and Path(index).exists():
        try:
            with ChangeIndex(index, create=False) as idx:
                index_crs = idx.crs
        except StreetcdError:
            raise
        except Exception as exc:  # sqlite3 errors of a file that is not an index
            raise InputError(f"{index}: cannot be read as a change index ({exc})") from None
        if index_crs:
            stated.append((f"change index {index}", index_crs))
    for (what, crs), (other, other_crs) in zip(stated, stated[1:], strict=False):
        if crs != other_crs:
            raise CRSMismatchError(f"crs: {what} is in {crs}, {other} in {other_crs}")
    return stated[0][1] if stated else None


def _unmatched(
    files: dict[str, Path], posed: dict[str, View], poses: Path, images: Path
) -> list[str]:
    """Warnings for images without a pose and poses without an image."""
    out = []
    unposed = sorted(set(files) - set(posed))
    if unposed:
        out.append(
            f"{len(unposed)} image(s) have no pose in {poses} and will fail: {_some(unposed)}"
        )
    missing = sorted(set(posed) - set(files))
    if missing:
        out.append(
            f"{len(missing)} pose(s) have no image in {images} and will fail: {_some(missing)}"
        )
    return out


def _near_store(views: Sequence[View], tiles: TileStore, reach_m: float) -> dict[str, View]:
    """The views with at least one tile of the store within ``reach_m`` of their centre."""
    out = {}
    for v in views:
        x, y = float(v.center[0]), float(v.center[1])
        if (
            math.isfinite(x)
            and math.isfinite(y)
            and tiles.tiles_in_bbox(x - reach_m, y - reach_m, x + reach_m, y + reach_m)
        ):
            out[v.name] = v
    return out


def _image_sizes(
    views: Sequence[View], files: dict[str, Path], max_pixels: int
) -> tuple[list[str], list[str], str]:
    """Each view's image header against its camera and the pixel limit: (notes, the views
    that will fail, the first one's error). Rescaled cameras are noted once per (image
    size, camera size)."""
    from streetcd.io.images import check_pixels, fits_camera, read_header

    rescaled: Counter[tuple[int, int, int, int]] = Counter()
    example: dict[tuple[int, int, int, int], str] = {}
    failing: list[str] = []
    first_error = ""
    for v in views:
        path = files[v.name]
        i = v.intrinsics
        try:
            header = read_header(path)
            check_pixels(path, header, max_pixels)
            if not fits_camera(header.width, header.height, i.width, i.height):
                raise InputError(
                    f"{path}: image is {header.width}x{header.height} but its camera says "
                    f"{i.width}x{i.height} (width, height), another aspect ratio"
                )
        except StreetcdError as exc:
            failing.append(v.name)
            first_error = first_error or str(exc)
            continue
        if (header.width, header.height) != (i.width, i.height):
            key = (header.width, header.height, i.width, i.height)
            rescaled[key] += 1
            example.setdefault(key, v.name)
    notes = [
        f"{n} image(s) are {w}x{h} where their camera says {cw}x{ch} (e.g. {example[w, h, cw, ch]}):"
        f" the same camera at {w / cw:.4g}x, intrinsics rescaled"
        for (w, h, cw, ch), n in sorted(rescaled.items())
    ]
    return notes, failing, first_error


def _class_codes(
    tiles: TileStore,
    views: Sequence[View],
    reach_m: float,
    warnings: list[str],
    params: DetectParams,
) -> list[str]:
    """A note of the class codes of the store's points near ``views`` (share of points,
    each with the role ``params.classes`` gives it); a warning when too few are in a role the
    detector uses, a note when most are in no role, and one when the reference-colour check
    will leave the ground out because the codes do not tell the road from it (the
    detector's own checks, :func:`streetcd.detect.roles.useless_codes`,
    :func:`~streetcd.detect.roles.roleless_codes` and
    :func:`~streetcd.detect.roles.road_told_codes`: said here once for the night, not by
    every worker)."""
    import numpy as np

    from streetcd.detect.roles import road_told_codes, role_of_code, roleless_codes, useless_codes

    class_map = params.classes

    counts: Counter[int] = Counter()
    seen: set[str] = set()
    for v in views:
        x, y = float(v.center[0]), float(v.center[1])
        for t in tiles.tiles_in_bbox(x - reach_m, y - reach_m, x + reach_m, y + reach_m):
            if t.id not in seen:
                seen.add(t.id)
                counts.update(t.classes)
    total = sum(counts.values()) or 1
    by_code = np.zeros(256, np.int64)
    for code, n in counts.items():
        by_code[code] = n
    notes = []
    useless = useless_codes(by_code, class_map)
    if useless is not None:
        warnings.append(useless)
    else:
        roleless = roleless_codes(by_code, class_map)
        if roleless is not None:
            notes.append(roleless)
    ap = params.appearance
    untold = road_told_codes(by_code, class_map) if ap.enabled and ap.ground_classes else None
    if untold is not None:
        notes.append(
            "the reference-colour check leaves the ground out (appearance.ground_classes): "
            f"{untold}"
        )
    shares = ", ".join(
        f"{role_of_code(c, class_map) or 'code'} {c} {100 * n / total:.0f} %"
        for c, n in counts.most_common()
    )
    return [f"class codes near the views ({len(seen)} tiles): {shares}", *notes]


def _some(names: object) -> str:
    """The first few of ``names`` (sorted), and how many more."""
    listed = sorted(names)  # type: ignore[call-overload]
    text = ", ".join(listed[:NAMES_SHOWN])
    return text + (f" and {len(listed) - NAMES_SHOWN} more" if len(listed) > NAMES_SHOWN else "")


def _span(views: Sequence[View], axis: int) -> str:
    values = [float(v.center[axis]) for v in views]
    return f"{min(values) + 0.0:.0f}..{max(values) + 0.0:.0f}".replace("-0..", "0..")


def _store_span(tiles: TileStore, axis: int) -> str:
    # the grid cells the store occupies (tile corners), enough to show where it lies
    cells = tiles._ij[:, axis] * tiles.tile_size_m
    return f"{cells.min():.0f}..{cells.max() + tiles.tile_size_m:.0f}"
