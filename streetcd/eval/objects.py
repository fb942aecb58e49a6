"""Scoring an index's change objects against a synthetic scene's truth (issue 17, item 5) or
an annotated case's labelled objects.

``streetcd run`` writes a change index: flagged views with their masks, regions and the
change objects merged from them (:mod:`streetcd.store.objects`). This module reads that index
and the scene's truth (``manifest.json``, ``truth/<stem>.instances.png`` and
``truth/<stem>.dontcare.png``; for a case ``gt/<stem>.labels.png`` and
``gt/<stem>.dontcare.png`` with case.json's object names, :func:`score_case_index`) and says

* where the flagged pixels fall: on a true change, on a don't-care disturbance (a parked car
  that came or went, a pedestrian, grown foliage) or elsewhere; for all flagged pixels, for
  the pixels of the objects reported as changes of the street (``transient`` null) and for
  those of the objects kept out as transients;
* which objects match which of the manifest's changes, and from that the object-level
  precision and recall and how many changes are matched by exactly one object;
* why each transient was kept out, and how many of its pixels were on a true change.

A region's pixels are found again from the view's mask: the detector labels the mask's
8-connected components with OpenCV (:func:`streetcd.detect.regions.changed_regions`), and
the index records those labels with each object's views. Nothing here runs the detector.
"""

from __future__ import annotations

import json
import math
import sqlite3
import statistics
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from streetcd.errors import CorruptFileError, InputError, MissingInputError

# An object matches a change when at least this share of its pixels lies on that change (and
# no other change has more of them). A quarter, not a half: a change's region is often grown
# by misregistration onto the wall around it, and a board beside a parked car can be one
# region of which the board is a third.
MATCH_FRACTION = 0.25


@dataclass(frozen=True)
class Where:
    """Where flagged pixels fall: ``change`` on a true change, ``dontcare`` on a
    disturbance, ``elsewhere`` on neither (a false alarm). Counts of pixels."""

    change: int = 0
    dontcare: int = 0
    elsewhere: int = 0

    @property
    def total(self) -> int:
        return self.change + self.dontcare + self.elsewhere

    def __add__(self, other: Where) -> Where:
        return Where(
            self.change + other.change,
            self.dontcare + other.dontcare,
            self.elsewhere + other.elsewhere,
        )

    def as_dict(self) -> dict[str, Any]:
        return {
            "pixels": self.total,
            "on_change": self.change,
            "on_dontcare": self.dontcare,
            "elsewhere": self.elsewhere,
            "on_dontcare_pct": _pct(self.dontcare, self.total),
            "on_change_pct": _pct(self.change, self.total),
        }


@dataclass(frozen=True)
class ObjectScore:
    """One change object of the index against the truth. ``by_change`` maps a manifest
    change's instance id to the object's pixels on it; ``match`` is the change it matches
    (None: none, see :data:`MATCH_FRACTION`)."""

    id: str
    kind: str
    class_name: str
    transient: str | None
    where: Where
    by_change: dict[int, int]
    match: int | None
    views: tuple[str, ...]
    centroid: tuple[float, float, float] = (math.nan, math.nan, math.nan)  # the index's CRS

    def as_dict(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "kind": self.kind,
            "class_name": self.class_name,
            "transient": self.transient,
            "match": self.match,
            "by_change": {str(k): v for k, v in sorted(self.by_change.items())},
            "views": list(self.views),
            **self.where.as_dict(),
        }


@dataclass(frozen=True)
class ChangeScore:
    """One change of the manifest: its pixels in the truth of every view of the scene, how
    many of them were flagged, how many are in objects reported as changes, and the objects matching it
    (reported ones in ``objects``, transients in ``kept_out``)."""

    instance_id: int
    kind: str
    type: str
    truth_px: int
    flagged_px: int
    reported_px: int
    objects: tuple[str, ...]
    kept_out: tuple[str, ...]
    # how far (metres, horizontally) the centroid of the reported object holding most of its
    # pixels lies from its box (0 inside); None without a box or a reported object
    position_error_m: float | None = None

    def as_dict(self) -> dict[str, Any]:
        return {
            "instance_id": self.instance_id,
            "kind": self.kind,
            "type": self.type,
            "truth_px": self.truth_px,
            "flagged_px": self.flagged_px,
            "reported_px": self.reported_px,
            "objects": list(self.objects),
            "kept_out": list(self.kept_out),
            "position_error_m": self.position_error_m,
        }


@dataclass(frozen=True)
class ViewFlags:
    """Which of the index's done views of the scene or case the run flagged, by whether
    their truth has a change (outside don't-care): issue 16's per-view rates on the path a
    night takes, not the flag rule applied to one detection (``evaluate --case``'s)."""

    with_change: int = 0
    with_change_flagged: int = 0
    without_change: int = 0
    without_change_flagged: int = 0

    def as_dict(self) -> dict[str, Any]:
        return {
            "with_change": self.with_change,
            "with_change_flagged": self.with_change_flagged,
            "with_change_flagged_pct": _pct(self.with_change_flagged, self.with_change),
            "without_change": self.without_change,
            "without_change_flagged": self.without_change_flagged,
            "without_change_flagged_pct": _pct(self.without_change_flagged, self.without_change),
        }


@dataclass(frozen=True)
class IndexScore:
    """The whole scoring of an index against a scene (see the module docstring)."""

    scene: str
    index: str
    flagged: Where  # every flagged pixel of the flagged views
    reported: Where  # the pixels of the objects reported as changes
    kept_out: Where  # the pixels of the objects kept out as transients
    flagged_views: int
    views_without_change: int  # flagged views with no flagged pixel on a true change
    objects: tuple[ObjectScore, ...]
    changes: tuple[ChangeScore, ...]
    skipped_views: tuple[str, ...] = field(default=())  # flagged, but not in the manifest
    view_flags: ViewFlags = field(default_factory=ViewFlags)  # the index's done views

    @property
    def reported_objects(self) -> list[ObjectScore]:
        return [o for o in self.objects if o.transient is None]

    def as_dict(self) -> dict[str, Any]:
        reported = self.reported_objects
        matched = [o for o in reported if o.match is not None]
        found = [c for c in self.changes if c.objects]
        truth = sum(c.truth_px for c in self.changes)
        reasons: dict[str, dict[str, int]] = {}
        for o in self.objects:
            if o.transient is not None:
                r = reasons.setdefault(_reason_kind(o.transient), {"objects": 0, "pixels": 0})
                r["objects"] += 1
                r["pixels"] += o.where.total
                r["on_change"] = r.get("on_change", 0) + o.where.change
        return {
            "scene": self.scene,
            "index": self.index,
            "flagged_views": self.flagged_views,
            "flagged_views_without_change": self.views_without_change,
            "skipped_views": list(self.skipped_views),
            "views": self.view_flags.as_dict(),
            "pixels": {
                "flagged": self.flagged.as_dict(),
                "reported": self.reported.as_dict(),
                "kept_out": self.kept_out.as_dict(),
                "true_change_kept_pct": _pct(self.reported.change, self.flagged.change),
                "truth_flagged_pct": _pct(self.flagged.change, truth),
                "truth_reported_pct": _pct(self.reported.change, truth),
            },
            "objects_total": len(self.objects),
            "objects_reported": len(reported),
            "objects_kept_out": len(self.objects) - len(reported),
            "changes_total": len(self.changes),
            "changes_found": len(found),
            "changes_one_object": sum(len(c.objects) == 1 for c in self.changes),
            "object_precision_pct": _pct(len(matched), len(reported)),
            "object_recall_pct": _pct(len(found), len(self.changes)),
            "position_error_m": _errors_summary(self.changes),
            "transient_reasons": reasons,
            "changes": [c.as_dict() for c in self.changes],
            "objects": [o.as_dict() for o in self.objects],
        }


def _pct(a: int, b: int) -> float | None:
    return None if b == 0 else round(100.0 * a / b, 2)


def _reason_kind(reason: str) -> str:
    """A transient's reason without its numbers (``seen by one view only; 3 view(s) ...``
    → ``seen by one view only``), to count objects by reason."""
    return reason.split(";")[0].split(":")[0].split(" (")[0].strip()


# --- reading ------------------------------------------------------------------------------


def read_manifest(scene: str | Path) -> dict[str, Any]:
    """The scene's ``manifest.json``; MissingInputError / CorruptFileError naming it."""
    path = Path(scene) / "manifest.json"
    if not path.exists():
        raise MissingInputError(f"{scene}: not a synthetic scene (no manifest.json)")
    try:
        manifest = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CorruptFileError(f"{path}: not valid JSON: {exc}") from None
    for key in ("views", "changes"):
        if not isinstance(manifest.get(key), list):
            raise CorruptFileError(f"{path}: field {key!r} must be a list")
    return manifest


def _read_png(path: Path, what: str) -> np.ndarray:
    """(H, W) single-channel image as stored (uint8 or uint16)."""
    import cv2

    if not path.exists():
        raise MissingInputError(f"{what} not found: {path}")
    a = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if a is None or a.ndim != 2:
        raise CorruptFileError(f"{path}: not a single-channel {what}")
    return a


def _mask_labels(path: Path, n_regions: int) -> np.ndarray:
    """(H, W) int32 region labels of a view's mask, as the detector numbered them (OpenCV's
    8-connected components, :func:`streetcd.detect.regions.changed_regions`)."""
    import cv2

    mask = _read_png(path, "change mask") > 0
    n, labels = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8, ltype=cv2.CV_32S)
    if n - 1 != n_regions:
        raise CorruptFileError(
            f"{path}: the mask has {n - 1} regions, the index lists {n_regions} for its view"
        )
    return labels


def _resolve(path: str, index_path: Path) -> Path:
    """A mask path as the index stored it (``streetcd run`` stores absolute paths), or
    relative to the working folder or to the index's folder (the run folder, where the
    index is written)."""
    p = Path(path)
    if p.is_absolute() or p.exists() or not (index_path.parent / p).exists():
        return p
    return index_path.parent / p


@dataclass
class _Truth:
    inst: np.ndarray  # (H, W) uint8/uint16 change instance id, 0 = none
    dontcare: np.ndarray  # (H, W) bool


def _truth(scene: Path, record: dict[str, Any]) -> _Truth:
    stem = Path(record["name"]).stem
    inst_path = scene / record.get("instances", f"truth/{stem}.instances.png")
    dc_path = scene / record.get("dontcare", f"truth/{stem}.dontcare.png")
    inst = _read_png(inst_path, "instance mask")
    dontcare = _read_png(dc_path, "don't-care mask") > 0
    if inst.shape != dontcare.shape:
        raise CorruptFileError(f"{dc_path}: {dontcare.shape} pixels, {inst_path}: {inst.shape}")
    return _Truth(inst, dontcare & (inst == 0))


def _case_truth(mask_path: Path, dontcare_path: Path, labels_path: Path | None) -> _Truth:
    """One view of an annotated case: its labels outside don't-care, and its don't-care.
    A view without a labels file may have no change (an all-zero mask), nothing else."""
    dontcare = _read_png(dontcare_path, "don't-care mask") > 0
    if labels_path is None:
        if np.any(_read_png(mask_path, "change mask")):
            raise MissingInputError(
                f"{mask_path.with_name(mask_path.name.replace('.mask.', '.labels.'))}: labels"
                f" not found, and {mask_path.name} has changed pixels"
            )
        labels = np.zeros(dontcare.shape, np.int32)
    else:
        labels = _read_png(labels_path, "labels image").astype(np.int32)
    if labels.shape != dontcare.shape:
        raise CorruptFileError(
            f"{dontcare_path}: {dontcare.shape} pixels, {labels_path}: {labels.shape}"
        )
    return _Truth(np.where(dontcare, 0, labels), dontcare)


def _per_change(inst: np.ndarray) -> dict[int, int]:
    """Pixels per change instance of an (H, W) instance image (0: none)."""
    ids, counts = np.unique(inst[inst > 0], return_counts=True)
    return {int(i): int(c) for i, c in zip(ids, counts, strict=True)}


def _where(pixels: np.ndarray, truth: _Truth) -> tuple[Where, dict[int, int]]:
    """Where the (H, W) bool ``pixels`` fall, and their count per change instance."""
    by_change = _per_change(truth.inst[pixels])
    n_change = sum(by_change.values())
    n_dc = int(np.count_nonzero(truth.dontcare[pixels]))
    where = Where(n_change, n_dc, int(np.count_nonzero(pixels)) - n_change - n_dc)
    return where, by_change


def _match(by_change: dict[int, int], total: int) -> int | None:
    """The change holding the most of an object's pixels, if at least MATCH_FRACTION."""
    if not by_change or total == 0:
        return None
    best = min(by_change, key=lambda k: (-by_change[k], k))
    return best if by_change[best] >= MATCH_FRACTION * total else None


# --- scoring ------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Change:
    """A change of the truth: its id (the truth's instance or label number), kind, type and
    its pixels in the truth of every view (flagged or not)."""

    id: int
    kind: str
    type: str
    truth_px: int
    box: tuple[float, ...] | None = None  # (min x, y, z, max x, y, z) in the index's CRS


def score_index(scene: str | Path, index_path: str | Path) -> IndexScore:
    """Score the change objects of ``index_path`` (a ``streetcd run`` index) against the
    synthetic scene folder ``scene``. The index's flagged views are matched to the
    manifest's views by image name; views of other images are listed in ``skipped_views``
    (InputError when no flagged view is of the scene). The index is opened read-only; one
    view's mask and truth are in memory at a time."""
    scene, index_path = Path(scene), Path(index_path)
    _check_index(index_path)
    manifest = read_manifest(scene)
    records = {Path(str(r["name"])).name: r for r in manifest["views"]}
    truth_px = _truth_pixels(manifest)
    changes = [
        _Change(
            int(c["instance_id"]),
            str(c.get("kind", "")),
            str(c.get("type", "")),
            truth_px.get(int(c["instance_id"]), 0),
            _box_in_crs(c.get("bbox_local"), manifest.get("origin")),
        )
        for c in manifest["changes"]
    ]
    truths = {name: partial(_truth, scene, r) for name, r in records.items()}
    changed = {name for name, r in records.items() if any((r.get("changed_pixels") or {}).values())}
    return _score(scene, index_path, truths, changes, changed)


def score_case_index(case: str | Path, index_path: str | Path) -> IndexScore:
    """Score the change objects of ``index_path`` (a ``streetcd run`` of an annotated case's
    images) against the case's labelled ground truth (``gt/<stem>.labels.png``, the object
    numbers of case.json; the layout of :mod:`streetcd.eval.case`), as :func:`score_index`
    does against a synthetic scene. A pixel on don't-care is a disturbance even where a label
    covers it (``streetcd evaluate --case`` does not score it either). Reads ``gt/`` and
    case.json only: not the cloud, not the poses."""
    from streetcd.eval.case import labelled_truth

    case, index_path = Path(case), Path(index_path)
    _check_index(index_path)
    labelled = labelled_truth(case)
    truths = {name: partial(_case_truth, *paths) for name, paths in labelled.views.items()}
    totals: dict[int, int] = {}
    changed = set()
    # each change's pixels in every view, flagged or not (a flagged view's truth is read
    # again when it is scored: one view's truth in memory at a time, as score_index)
    for name, load in truths.items():
        in_view = _per_change(load().inst)
        _add(totals, in_view)
        if in_view:
            changed.add(name)
    changes = [
        _Change(
            label,
            labelled.objects.get(label, ("", ""))[1],
            labelled.objects.get(label, (f"object {label}", ""))[0],
            totals.get(label, 0),
        )
        for label in sorted(set(labelled.objects) | set(totals))
    ]
    return _score(case, index_path, truths, changes, changed)


def _check_index(index_path: Path) -> None:
    if not index_path.exists():
        raise MissingInputError(f"change index not found: {index_path}")


def _score(
    source: Path,
    index_path: Path,
    truths: Mapping[str, Callable[[], _Truth]],
    changes: Sequence[_Change],
    changed: Collection[str],
) -> IndexScore:
    """:func:`score_index` against ``truths`` (image name -> its truth, read when called);
    ``changed`` names the images whose truth has a change."""
    from streetcd.store.index import ChangeIndex
    from streetcd.store.objects import list_objects

    with ChangeIndex(index_path, readonly=True) as idx:
        flagged = idx.conn.execute(
            "SELECT f.view, f.mask_path, f.n_regions, coalesce(v.image, f.view) AS image"
            " FROM flagged f LEFT JOIN views v ON v.view = f.view ORDER BY f.view"
        ).fetchall()
        done = idx.conn.execute(
            "SELECT coalesce(image, view) AS image, flagged FROM views WHERE status = 'done'"
        ).fetchall()
    objects = list_objects(index_path, sort="id")
    # Per view key: (object's position in ``objects``, its region labels there).
    in_view: dict[str, list[tuple[int, list[int]]]] = {}
    for k, o in enumerate(objects):
        for ov in o["views"]:
            if ov["sees_change"]:
                in_view.setdefault(ov["view"], []).append((k, ov["labels"]))

    tally = _Tally(len(objects))
    skipped = []
    for row in flagged:
        image = _image_name(row["image"])
        if image not in truths:
            skipped.append(row["view"])
            continue
        if row["mask_path"] is None:
            raise CorruptFileError(f"{index_path}: flagged view {row['view']!r} has no mask_path")
        labels = _mask_labels(_resolve(row["mask_path"], index_path), row["n_regions"])
        truth = truths[image]()
        if labels.shape != truth.inst.shape:
            raise CorruptFileError(
                f"{row['mask_path']}: {labels.shape} pixels, the truth of {image}"
                f" {truth.inst.shape}"
            )
        tally.add_view(labels, truth, objects, in_view.get(row["view"], []), image)
    if flagged and tally.n_views == 0:
        raise InputError(
            f"{index_path}: none of its {len(flagged)} flagged views is an image of {source}"
        )
    return tally.score(
        source, index_path, changes, objects, tuple(skipped), _view_flags(done, truths, changed)
    )


def _view_flags(
    done: Sequence[sqlite3.Row], truths: Mapping[str, object], changed: Collection[str]
) -> ViewFlags:
    """:class:`ViewFlags` of the index's done views that are images of the truth."""
    with_change, without = [0, 0], [0, 0]  # views, of them flagged
    for row in done:
        image = _image_name(row["image"])
        if image not in truths:
            continue
        tally = with_change if image in changed else without
        tally[0] += 1
        tally[1] += int(bool(row["flagged"]))
    return ViewFlags(with_change[0], with_change[1], without[0], without[1])


def _image_name(key: object) -> str:
    """The image's file name of a view key (``name#content-hash``) or image path."""
    return Path(str(key).split("#")[0]).name


def _add(into: dict[int, int], more: dict[int, int]) -> None:
    for k, n in more.items():
        into[k] = into.get(k, 0) + n


class _Tally:
    """Pixel counts gathered view by view: of all flagged pixels, of each object's, and of
    the pixels of reported objects and of transients (each pixel once)."""

    def __init__(self, n_objects: int) -> None:
        self.n_views = 0
        self.without_change = 0
        self.flagged, self.reported, self.kept_out = Where(), Where(), Where()
        self.flagged_by_change: dict[int, int] = {}
        self.reported_by_change: dict[int, int] = {}
        self.where = [Where() for _ in range(n_objects)]
        self.by_change: list[dict[int, int]] = [{} for _ in range(n_objects)]
        self.views: list[list[str]] = [[] for _ in range(n_objects)]

    def add_view(
        self,
        labels: np.ndarray,
        truth: _Truth,
        objects: Sequence[dict],
        members: Sequence[tuple[int, list[int]]],
        image: str,
    ) -> None:
        """One flagged view: ``labels`` its (H, W) region labels, ``members`` the objects
        with regions in it (their position in ``objects`` and their labels)."""
        self.n_views += 1
        w, by = _where(labels > 0, truth)
        self.flagged += w
        self.without_change += int(w.change == 0)
        _add(self.flagged_by_change, by)
        reported = np.zeros(labels.shape, bool)
        kept = np.zeros(labels.shape, bool)
        for k, labs in members:
            pix = np.isin(labels, np.asarray(labs, dtype=np.int32))
            (reported if objects[k]["transient"] is None else kept)[...] |= pix
            w, by = _where(pix, truth)
            self.where[k] += w
            _add(self.by_change[k], by)
            self.views[k].append(image)
        w, by = _where(reported, truth)
        self.reported += w
        _add(self.reported_by_change, by)
        self.kept_out += _where(kept & ~reported, truth)[0]

    def score(
        self,
        scene: Path,
        index_path: Path,
        changes: Sequence[_Change],
        objects: Sequence[dict],
        skipped: tuple[str, ...],
        view_flags: ViewFlags,
    ) -> IndexScore:
        scores = tuple(
            ObjectScore(
                o["id"],
                o["kind"],
                o["class_name"],
                o["transient"],
                self.where[k],
                self.by_change[k],
                _match(self.by_change[k], self.where[k].total),
                tuple(sorted(self.views[k])),
                _xyz(o["centroid"]),
            )
            for k, o in enumerate(objects)
            if self.views[k]  # objects of views of another scene are left out
        )
        scored = tuple(
            ChangeScore(
                c.id,
                c.kind,
                c.type,
                c.truth_px,
                self.flagged_by_change.get(c.id, 0),
                self.reported_by_change.get(c.id, 0),
                tuple(o.id for o in scores if o.match == c.id and o.transient is None),
                tuple(o.id for o in scores if o.match == c.id and o.transient is not None),
                _position_error(c, scores),
            )
            for c in changes
        )
        return IndexScore(
            str(scene),
            str(index_path),
            self.flagged,
            self.reported,
            self.kept_out,
            self.n_views,
            self.without_change,
            scores,
            scored,
            skipped,
            view_flags,
        )


def _xyz(point: Sequence[float]) -> tuple[float, float, float]:
    return float(point[0]), float(point[1]), float(point[2])


def _box_in_crs(box_local: Any, origin: Any) -> tuple[float, ...] | None:
    """A manifest change's ``bbox_local`` (6 numbers, the scene's local frame) in the CRS the
    index is in (the local frame plus the manifest's ``origin``); None without either."""
    if not isinstance(box_local, list) or len(box_local) != 6 or not isinstance(origin, list):
        return None
    o = [float(v) for v in origin[:3]]
    return tuple(float(v) + o[k % 3] for k, v in enumerate(box_local))


def _position_error(change: _Change, scores: Sequence[ObjectScore]) -> float | None:
    """The horizontal distance (metres) from the centroid of the reported object holding the
    most of ``change``'s pixels to the change's box (0 inside); None without a box or a
    reported object matching it."""
    mine = [o for o in scores if o.match == change.id and o.transient is None]
    if change.box is None or not mine:
        return None
    best = max(mine, key=lambda o: (o.by_change.get(change.id, 0), o.id))
    x, y = best.centroid[0], best.centroid[1]
    lo_x, lo_y, _, hi_x, hi_y, _ = change.box
    dx = max(lo_x - x, 0.0, x - hi_x)
    dy = max(lo_y - y, 0.0, y - hi_y)
    return round(math.hypot(dx, dy), 3)


def _errors_summary(changes: Sequence[ChangeScore]) -> dict[str, Any]:
    """The found changes' position errors: how many were measured, their median and largest."""
    errors = sorted(c.position_error_m for c in changes if c.position_error_m is not None)
    if not errors:
        return {"measured": 0, "median": None, "max": None}
    return {"measured": len(errors), "median": statistics.median(errors), "max": errors[-1]}


def _truth_pixels(manifest: dict[str, Any]) -> dict[int, int]:
    """Each change's pixels in the truth of every view of the scene (the manifest's
    ``views[i].changed_pixels``), flagged or not."""
    out: dict[int, int] = {}
    for r in manifest["views"]:
        for k, n in (r.get("changed_pixels") or {}).items():
            out[int(k)] = out.get(int(k), 0) + int(n)
    return out
