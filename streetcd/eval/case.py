"""Evaluation on annotated cases: real streets that a city annotated itself, scored like the
synthetic scenes (paper §5, eq. 12) and, per view, by the nightly run's flag rule.

A case is a folder (the layout of ``../shared/cases``, see its README)::

    images/                  the newer photographs
    sparse/                  their poses: COLMAP text or binary (sparse/0/ also), or a pose
                             file streetcd reads named by case.json "poses", or poses.csv (OPK)
    cloud/*.laz|las          the older point cloud (all files, one local frame)
    gt/<stem>.mask.png       255 where the scene differs from the old cloud (uint8 0/255)
    gt/<stem>.dontcare.png   255 where the comparison is not scored
    gt/<stem>.labels.png     optional: the change's object number per pixel (0: none)
    case.json                optional: "objects" [{id, type, ...}] naming the label numbers
                             (or "inserted_objects" [{type, ...}], label = position + 1),
                             "poses" (a pose file or folder relative to the case)

Every view of the pose file needs its image and its two ground-truth masks. The detector
sees the images, the poses and the cloud; ``gt/`` is read only for scoring. Without labels,
the ground-truth change segments of GDR are the 8-connected components of each view's mask.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage

from streetcd.config import Config, RunParams, params_to_dict
from streetcd.detect.cache import SurfaceCache
from streetcd.detect.chain import DetectionResult, detect_view
from streetcd.errors import (
    CorruptFileError,
    CRSMismatchError,
    EmptyViewError,
    InputError,
    MissingInputError,
)
from streetcd.eval.evaluate import Progress, read_mask
from streetcd.eval.metrics import Summary, TypeRow, ViewScore, per_type_table, score_view, summarize
from streetcd.geometry.neighbours import select_neighbours
from streetcd.io.images import read_image
from streetcd.io.las import load_clouds
from streetcd.io.poses import read_poses
from streetcd.run.worker import is_flagged
from streetcd.types import PointCloud, View

MIN_COVER = 0.5  # the paper's object rule, as metrics.score_view applies it
_EIGHT = np.ones((3, 3), dtype=bool)


# ---------------------------------------------------------------------------------------------
# Loading (I/O edge)


@dataclass(frozen=True)
class CaseView:
    """One annotated view: its pose and the paths of its image and ground truth."""

    view: View
    image: Path
    mask: Path
    dontcare: Path
    labels: Path | None = None

    @property
    def name(self) -> str:
        return self.view.name


@dataclass(frozen=True)
class Case:
    """An annotated case on disk: views (pose-file order), the reference cloud, case.json."""

    root: Path
    views: tuple[CaseView, ...]
    cloud: PointCloud
    manifest: dict[str, Any] = field(default_factory=dict)
    objects: dict[int, str] = field(default_factory=dict)  # label number -> object type
    poses: Path | None = None

    @property
    def has_labels(self) -> bool:
        return any(v.labels is not None for v in self.views)


def _manifest(root: Path) -> dict[str, Any]:
    path = root / "case.json"
    if not path.exists():
        return {}
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise CorruptFileError(f"{path}: not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: must hold a JSON object, got {type(data).__name__}")
    return data


def _pose_source(root: Path, manifest: Mapping[str, Any]) -> Path:
    named = manifest.get("poses")
    if named is not None:
        if not isinstance(named, str):
            raise InputError(f"{root / 'case.json'}: field 'poses' must be a path, got {named!r}")
        path = root / named
        if not path.exists():
            raise MissingInputError(f"{path}: pose file named by {root / 'case.json'} not found")
        return path
    for folder in (root / "sparse", root / "sparse" / "0"):
        if (folder / "images.txt").exists() or (folder / "images.bin").exists():
            return folder
    if (root / "poses.csv").exists():
        return root / "poses.csv"
    raise MissingInputError(
        f"{root}: no poses (expected sparse/images.txt with sparse/cameras.txt, "
        "sparse/images.bin, or poses.csv)"
    )


def _objects(root: Path, manifest: Mapping[str, Any]) -> dict[int, str]:
    """Label number -> object type from case.json ("objects" with ids, or "inserted_objects"
    numbered from 1 in their order)."""
    path = root / "case.json"
    if "objects" in manifest:
        entries, numbered = manifest["objects"], False
    elif "inserted_objects" in manifest:
        entries, numbered = manifest["inserted_objects"], True
    else:
        return {}
    key = "inserted_objects" if numbered else "objects"
    if not isinstance(entries, list):
        raise InputError(f"{path}: field {key!r} must be a list, got {type(entries).__name__}")
    out: dict[int, str] = {}
    for i, ob in enumerate(entries):
        if not isinstance(ob, dict):
            raise InputError(f"{path}: field '{key}[{i}]' must be an object, got {ob!r}")
        if numbered:
            label = i + 1
        else:
            raw = ob.get("id", ob.get("label"))
            if isinstance(raw, bool) or not isinstance(raw, int) or raw <= 0:
                raise InputError(
                    f"{path}: field '{key}[{i}].id' must be a positive label number, got {raw!r}"
                )
            label = raw
        out[label] = str(ob.get("type", f"object {label}"))
    return out


def load_case(root: str | Path) -> Case:
    """Read a case folder (layout in the module docstring): poses, the cloud, case.json, and
    the paths of every view's image and ground truth, all checked to exist.

    Raises MissingInputError naming the first missing file or folder, CorruptFileError /
    InputError naming the file and the field of malformed input, CRSMismatchError when the
    poses and the cloud state different CRSs.
    """
    root = Path(root)
    if not root.is_dir():
        raise MissingInputError(f"case folder not found: {root}")
    manifest = _manifest(root)
    images = root / "images"
    if not images.is_dir():
        raise MissingInputError(f"{images}: image folder not found")
    gt = root / "gt"
    if not gt.is_dir():
        raise MissingInputError(f"{gt}: ground-truth folder not found")
    source = _pose_source(root, manifest)
    poses = read_poses(source, image_dir=images)
    views = []
    for v in poses.views:
        image = images / v.name
        if not image.exists():
            raise MissingInputError(f"{image}: image of view {v.name!r} ({poses.source}) not found")
        paths = {kind: gt / f"{v.stem}.{kind}.png" for kind in ("mask", "dontcare", "labels")}
        for kind in ("mask", "dontcare"):
            if not paths[kind].exists():
                raise MissingInputError(
                    f"{paths[kind]}: ground-truth {kind} of view {v.name!r} not found"
                )
        labels = paths["labels"] if paths["labels"].exists() else None
        views.append(CaseView(v, image, paths["mask"], paths["dontcare"], labels))
    if not views:
        raise InputError(f"{poses.source}: no views")
    files = sorted(p for p in (root / "cloud").glob("*") if p.suffix.lower() in (".las", ".laz"))
    if not files:
        raise MissingInputError(f"{root / 'cloud'}: no LAS/LAZ files")
    cloud = load_clouds(files)
    if poses.crs and cloud.crs and poses.crs != cloud.crs:
        raise CRSMismatchError(f"poses {poses.source} are in {poses.crs}, the cloud in {cloud.crs}")
    return Case(root, tuple(views), cloud, manifest, _objects(root, manifest), poses.source)


@dataclass(frozen=True)
class LabelledTruth:
    """A case's ground truth without its cloud and poses, for scoring a run's change index
    (:func:`streetcd.eval.objects.score_case_index`): ``views`` maps an image name of
    ``images/`` to its ``(mask, dontcare, labels)`` paths in ``gt/`` (labels None where the
    view has none); ``objects`` is case.json's label number -> (object type, kind), the kind
    "" unless an entry names it."""

    root: Path
    views: dict[str, tuple[Path, Path, Path | None]]
    objects: dict[int, tuple[str, str]]


def labelled_truth(root: str | Path) -> LabelledTruth:
    """Read a case's ``gt/`` and ``case.json`` only (layout in the module docstring): every
    image of ``images/`` with a ``gt/<stem>.mask.png``. MissingInputError naming a missing
    folder or don't-care mask; InputError when the case has no ``labels.png`` at all (a
    change object is matched to a labelled object: without labels there is none)."""
    root = Path(root)
    images, gt = root / "images", root / "gt"
    for folder, what in (
        (root, "case folder"),
        (images, "image folder"),
        (gt, "ground-truth folder"),
    ):
        if not folder.is_dir():
            raise MissingInputError(f"{folder}: {what} not found")
    manifest = _manifest(root)
    views: dict[str, tuple[Path, Path, Path | None]] = {}
    for image in sorted(p for p in images.iterdir() if p.is_file()):
        mask = gt / f"{image.stem}.mask.png"
        if not mask.exists():
            continue
        dontcare = gt / f"{image.stem}.dontcare.png"
        if not dontcare.exists():
            raise MissingInputError(
                f"{dontcare}: ground-truth dontcare of {image.name!r} not found"
            )
        labels = gt / f"{image.stem}.labels.png"
        views[image.name] = (mask, dontcare, labels if labels.exists() else None)
    if not views:
        raise InputError(f"{gt}: no <stem>.mask.png for any image of {images}")
    if all(labels is None for _, _, labels in views.values()):
        raise InputError(
            f"{gt}: no <stem>.labels.png: scoring change objects needs the changes' object "
            "numbers per pixel"
        )
    types = _objects(root, manifest)  # checks the entries
    key = "objects" if "objects" in manifest else "inserted_objects"
    kinds: dict[int, str] = {}
    for i, entry in enumerate(manifest.get(key, [])):
        label = entry.get("id", entry.get("label")) if key == "objects" else i + 1
        kinds[label] = str(entry.get("kind", ""))
    return LabelledTruth(root, views, {k: (t, kinds.get(k, "")) for k, t in types.items()})


@dataclass(frozen=True)
class Truth:
    """One view's ground truth: (H, W) bool ``mask`` and ``dontcare``, (H, W) int32
    ``instances`` (the labels, or the mask's 8-connected components without them)."""

    mask: np.ndarray
    dontcare: np.ndarray
    instances: np.ndarray


def read_truth(cv: CaseView) -> Truth:
    """The ground truth of one view, checked against its camera's image size."""
    shape = (cv.view.intrinsics.height, cv.view.intrinsics.width)
    mask = read_mask(cv.mask)
    dontcare = read_mask(cv.dontcare)
    if cv.labels is not None:
        instances = read_mask(cv.labels, np.int32)
    else:
        instances = ndimage.label(mask, structure=_EIGHT)[0].astype(np.int32)
    for path, a in ((cv.mask, mask), (cv.dontcare, dontcare), (cv.labels, instances)):
        if a.shape != shape:
            raise InputError(
                f"{path}: mask is {a.shape[1]}x{a.shape[0]}, the camera of view "
                f"{cv.name!r} is {shape[1]}x{shape[0]}"
            )
    return Truth(mask, dontcare, instances)


# ---------------------------------------------------------------------------------------------
# Per-view flags (the nightly run's rule) and per-object pixels: pure counts


@dataclass(frozen=True)
class ViewFlag:
    """What the run's flag rule makes of one view, and the pixels behind it.

    true_change : the ground truth has changed pixels outside dontcare.
    flagged : :func:`streetcd.run.worker.is_flagged` with the run's settings.
    detected_px / cared_px : detected pixels outside dontcare / pixels outside dontcare.
    detected_all_px / detected_dontcare_px : detected pixels / those on dontcare.
    """

    true_change: bool
    flagged: bool
    detected_px: int
    cared_px: int
    detected_all_px: int
    detected_dontcare_px: int


def view_flag(
    detected: np.ndarray,
    truth: np.ndarray,
    dontcare: np.ndarray,
    region_pixels: Sequence[int],
    run: RunParams,
    region_scores: Sequence[float] | None = None,
) -> ViewFlag:
    """Flag one view as the nightly run does and count its pixels.

    detected, truth, dontcare : (H, W) bool (or 0/255). region_pixels : pixels per changed
    region of the detection (:attr:`DetectionResult.regions`), region_scores : their scores
    (None: the rule's pixels alone). The changed fraction is the
    detected share of all H·W pixels, as the detector reports it.
    """
    det = np.asarray(detected).astype(bool, copy=False)
    gt = np.asarray(truth).astype(bool, copy=False)
    dc = np.asarray(dontcare).astype(bool, copy=False)
    if not det.shape == gt.shape == dc.shape or det.ndim != 2:
        raise InputError(
            f"detected {det.shape}, truth {gt.shape} and dontcare {dc.shape} must be one (H, W)"
        )
    n_all = int(np.count_nonzero(det))
    on_dc = int(np.count_nonzero(det & dc))
    return ViewFlag(
        true_change=bool(np.any(gt & ~dc)),
        flagged=is_flagged(n_all / det.size, list(region_pixels), det.size, run, region_scores),
        detected_px=n_all - on_dc,
        cared_px=int(det.size - np.count_nonzero(dc)),
        detected_all_px=n_all,
        detected_dontcare_px=on_dc,
    )


def _ratio(num: float, den: float) -> float:
    return num / den if den else math.nan


def _pct(x: float) -> float | None:
    return None if math.isnan(x) else 100.0 * x


def _none(x: float) -> float | None:
    return None if math.isnan(x) else x


def _mean(a: np.ndarray, where: np.ndarray) -> float:
    return float(a[where].mean()) if where.any() else math.nan


@dataclass(frozen=True)
class FlagSummary:
    """Per-view flags pooled over a case's views."""

    changed_views: int = 0  # views with a true change
    changed_flagged: int = 0  # ... that the rule flags
    unchanged_views: int = 0  # views without one
    unchanged_flagged: int = 0  # ... that the rule flags
    unchanged_detected_px: int = 0  # detected cared-for pixels on views without change
    unchanged_cared_px: int = 0  # cared-for pixels of views without change
    detected_px: int = 0  # detected pixels, dontcare included, all views
    detected_dontcare_px: int = 0  # ... of them on dontcare

    @property
    def changed_flag_rate(self) -> float:
        """Share of the views with a true change that are flagged (NaN without such views)."""
        return _ratio(self.changed_flagged, self.changed_views)

    @property
    def unchanged_flag_rate(self) -> float:
        """Share of the views without change that are flagged (false alarms)."""
        return _ratio(self.unchanged_flagged, self.unchanged_views)

    @property
    def unchanged_pixel_share(self) -> float:
        """Share of the cared-for pixels of views without change that are detected."""
        return _ratio(self.unchanged_detected_px, self.unchanged_cared_px)

    @property
    def dontcare_share(self) -> float:
        """Share of the detected pixels (all views) that lie on dontcare."""
        return _ratio(self.detected_dontcare_px, self.detected_px)

    def as_dict(self) -> dict[str, Any]:
        """Counts, and rates in percent (None where undefined)."""
        return {
            "changed_views": self.changed_views,
            "changed_flagged": self.changed_flagged,
            "changed_flagged_pct": _pct(self.changed_flag_rate),
            "unchanged_views": self.unchanged_views,
            "unchanged_flagged": self.unchanged_flagged,
            "unchanged_flagged_pct": _pct(self.unchanged_flag_rate),
            "unchanged_pixels_flagged_pct": _pct(self.unchanged_pixel_share),
            "flagged_on_dontcare_pct": _pct(self.dontcare_share),
        }


def summarize_flags(flags: Iterable[ViewFlag]) -> FlagSummary:
    """Pool per-view flags: views with and without change, flagged or not, and pixels."""
    c = [0] * 8
    for f in flags:
        if f.true_change:
            c[0] += 1
            c[1] += f.flagged
        else:
            c[2] += 1
            c[3] += f.flagged
            c[4] += f.detected_px
            c[5] += f.cared_px
        c[6] += f.detected_all_px
        c[7] += f.detected_dontcare_px
    return FlagSummary(*c)


def label_pixels(
    detected: np.ndarray, labels: np.ndarray, dontcare: np.ndarray
) -> dict[int, tuple[int, int]]:
    """Per ground-truth label (≠ 0): (its cared-for pixels, those the detection covers).

    detected, dontcare : (H, W) bool. labels : (H, W) integer label numbers.
    """
    care = ~np.asarray(dontcare).astype(bool, copy=False)
    ids = np.asarray(labels)[care].astype(np.int64)
    hits = np.asarray(detected).astype(bool, copy=False)[care]
    total = np.bincount(ids)
    covered = np.bincount(ids[hits], minlength=total.size)
    return {int(i): (int(total[i]), int(covered[i])) for i in np.flatnonzero(total) if i != 0}


@dataclass(frozen=True)
class ObjectScore:
    """One labelled object over the evaluated views.

    gt_px / found_px : its cared-for pixels / those detected, summed over views.
    views_counted : views where it has at least metrics' ``min_truth_px`` cared-for pixels;
    views_detected : of those, views where the detection covers ≥ 50 % of it. The object is
    detected (Table 2's NCDC rule) when that holds in at least half of its counted views.
    """

    label: int
    type: str
    gt_px: int = 0
    found_px: int = 0
    views_counted: int = 0
    views_detected: int = 0

    @property
    def recall(self) -> float:
        return _ratio(self.found_px, self.gt_px)

    @property
    def detected(self) -> bool:
        return self.views_counted > 0 and 2 * self.views_detected >= self.views_counted

    def as_dict(self) -> dict[str, Any]:
        return {
            "label": self.label,
            "type": self.type,
            "gt_px": self.gt_px,
            "found_px": self.found_px,
            "recall_pct": _pct(self.recall),
            "views_counted": self.views_counted,
            "views_detected": self.views_detected,
            "detected": self.detected,
        }


def object_scores(
    names: Mapping[int, str],
    pixels: Sequence[Mapping[int, tuple[int, int]]],
    scores: Sequence[ViewScore],
) -> tuple[ObjectScore, ...]:
    """Per object from each view's :func:`label_pixels` and :func:`score_view` coverage
    (only labelled views' scores carry label numbers); objects named in ``names`` that no
    view shows are listed with zeros."""
    labels = sorted(set(names) | {k for p in pixels for k in p})
    out = []
    for lab in labels:
        gt = sum(p.get(lab, (0, 0))[0] for p in pixels)
        found = sum(p.get(lab, (0, 0))[1] for p in pixels)
        covs = [s.coverage[lab] for s in scores if lab in s.coverage]
        out.append(
            ObjectScore(
                lab,
                names.get(lab, f"object {lab}"),
                gt,
                found,
                len(covs),
                sum(c >= MIN_COVER for c in covs),
            )
        )
    return tuple(out)


# ---------------------------------------------------------------------------------------------
# Evaluation


@dataclass(frozen=True)
class CaseViewOutcome:
    """One view of a case: its scores, its flag, and why the detector saw what it saw.

    neighbours : the chosen neighbours as (name, baseline in metres between the centres).
    used : those that gave evidence (saw reference points). surface_share : share of the
    view's pixels with a reference surface. evidence_share : share with evidence from at least
    one neighbour. largest_region_px : the detection's largest region. gt_px : the truth's
    cared-for changed pixels. truth_surface_share : share of those with a reference surface.
    raw_change_truth / raw_change_rest : mean raw change ``C_p`` (eq. 5, in [0, 1]) over the
    cared-for pixels on / off the truth (NaN where there are none): whether eq. 5 sees the
    change at all. error : why the view has no detection (it saw no reference point), else None.
    regions : the detection's regions as (pixels, score), as ``evaluate --scene`` lists them.
    """

    name: str
    score: ViewScore
    flag: ViewFlag
    seconds: float
    neighbours: tuple[tuple[str, float], ...] = ()
    used: tuple[str, ...] = ()
    surface_share: float = 0.0
    evidence_share: float = 0.0
    largest_region_px: int = 0
    gt_px: int = 0
    truth_surface_share: float = math.nan
    raw_change_truth: float = math.nan
    raw_change_rest: float = math.nan
    error: str | None = None
    regions: tuple[tuple[int, float], ...] = ()

    def as_dict(self) -> dict[str, Any]:
        used = set(self.used)
        return {
            "name": self.name,
            "true_change": self.flag.true_change,
            "gt_px": self.gt_px,
            "flagged_by_run": self.flag.flagged,
            "detected_px": self.flag.detected_px,
            "detected_dontcare_px": self.flag.detected_dontcare_px,
            "largest_region_px": self.largest_region_px,
            "regions": [list(r) for r in self.regions],
            **summarize([self.score]).as_dict(),
            "surface_pct": 100.0 * self.surface_share,
            "evidence_pct": 100.0 * self.evidence_share,
            "truth_surface_pct": _pct(self.truth_surface_share),
            "raw_change_truth": _none(self.raw_change_truth),
            "raw_change_rest": _none(self.raw_change_rest),
            "neighbours": [
                {"name": n, "baseline_m": round(b, 3), "used": n in used}
                for n, b in self.neighbours
            ],
            "seconds": self.seconds,
            "error": self.error,
        }


@dataclass(frozen=True)
class CaseReport:
    """Pooled scores (eq. 12), per object, per-view flags and per view, of one case."""

    case: str
    overall: Summary
    flags: FlagSummary
    objects: tuple[ObjectScore, ...]
    per_type: dict[str, TypeRow]
    views: tuple[CaseViewOutcome, ...]
    labelled: bool
    params: dict[str, Any] = field(default_factory=dict)

    @property
    def seconds_per_view(self) -> float:
        return float(np.mean([v.seconds for v in self.views])) if self.views else math.nan

    def as_dict(self) -> dict[str, Any]:
        """The JSON layout of ``streetcd evaluate --case``."""
        return {
            "case": self.case,
            "n_views": len(self.views),
            "overall": self.overall.as_dict(),
            "flags": self.flags.as_dict(),
            "labelled": self.labelled,
            "objects": [o.as_dict() for o in self.objects],
            "per_type": {
                t: {"ns": r.ns, "ngt": r.ngt, "ncdc": r.ncdc, "nfdc": r.nfdc}
                for t, r in self.per_type.items()
            },
            "seconds_per_view": self.seconds_per_view,
            "per_view": [v.as_dict() for v in self.views],
            "params": self.params,
        }


def evaluate_case(
    root: str | Path | Case,
    config: Config | None = None,
    *,
    max_views: int | None = None,
    progress: Progress | None = None,
) -> CaseReport:
    """Run the detector on every view of a case (or the first ``max_views`` in pose-file
    order) and score it: pooled eq. 12 rates, per object, and per-view flags with the run's
    rule (``config.run``). Neighbours are chosen among all the case's views as the detector's
    callers choose them (:func:`select_neighbours`, ``n_neighbours`` of ``config.detect``);
    one :class:`SurfaceCache` serves every view. A view that sees no reference point counts
    as detecting nothing, with its ``error`` kept. ``root``: the folder, or a loaded case.
    """
    config = Config() if config is None else config
    params = config.detect
    case = root if isinstance(root, Case) else load_case(root)
    todo = case.views if max_views is None else case.views[:max_views]
    if not todo:
        raise InputError(f"{case.root}: no views to evaluate")
    all_views = [cv.view for cv in case.views]
    paths = {cv.name: cv.image for cv in case.views}
    cache: dict[str, np.ndarray] = {}
    surfaces = SurfaceCache()

    def image_of(v: View) -> np.ndarray:
        if v.name not in cache:
            cache[v.name] = read_image(paths[v.name])
        return cache[v.name]

    outcomes: list[CaseViewOutcome] = []
    pixels: list[dict[int, tuple[int, int]]] = []
    for cv in todo:
        v = cv.view
        nbs = select_neighbours(
            v,
            all_views,
            n=params.correlate.n_neighbours,
            min_parallax_px=params.correlate.min_parallax_px,
        )
        keep = {v.name, *(n.name for n in nbs)}
        for name in list(cache):
            if name not in keep:
                del cache[name]
        truth = read_truth(cv)
        image = image_of(v)
        neighbours = [(image_of(n), n) for n in nbs]
        t0 = time.perf_counter()
        error: str | None = None
        result: DetectionResult | None
        try:
            result = detect_view(image, v, neighbours, case.cloud, params, surfaces=surfaces)
        except EmptyViewError as exc:
            result, error = None, str(exc)
        seconds = time.perf_counter() - t0
        if result is None:
            mask = np.zeros(truth.mask.shape, dtype=bool)
            regions: list[int] = []
            region_scores: list[float] | None = None
            classes = None
        else:
            mask, classes = result.mask, result.classes
            regions = [g.pixels for g in result.regions]
            region_scores = [g.score for g in result.regions]
        score = score_view(mask, truth.mask, truth.instances, truth.dontcare, class_raster=classes)
        on_truth = truth.mask & ~truth.dontcare
        rest = ~truth.mask & ~truth.dontcare
        if result is None:
            diagnostics = (math.nan, math.nan, math.nan)
        else:
            diagnostics = (
                _mean(np.isfinite(result.depth), on_truth),
                _mean(result.raw_change, on_truth),
                _mean(result.raw_change, rest),
            )
        if cv.labels is not None:
            pixels.append(label_pixels(mask, truth.instances, truth.dontcare))
        outcomes.append(
            CaseViewOutcome(
                v.name,
                score,
                view_flag(mask, truth.mask, truth.dontcare, regions, config.run, region_scores),
                seconds,
                tuple((n.name, float(np.linalg.norm(n.center - v.center))) for n in nbs),
                () if result is None else tuple(result.neighbours),
                0.0 if result is None else float(np.isfinite(result.depth).mean()),
                0.0 if result is None else float((result.support > 0).mean()),
                max(regions, default=0),
                int(np.count_nonzero(on_truth)),
                *diagnostics,
                error,
                ()
                if result is None
                else tuple((int(g.pixels), round(float(g.score), 4)) for g in result.regions),
            )
        )
        if progress is not None:
            progress(v.name)
    scores = [o.score for o in outcomes]
    # coverage is keyed by label number on labelled views only (by component elsewhere), so
    # objects are found on those; false detections count on every view
    labelled = [
        o.score if cv.labels is not None else replace(o.score, coverage={})
        for o, cv in zip(outcomes, todo, strict=True)
    ]
    objects = object_scores(case.objects, pixels, labelled) if case.has_labels else ()
    types = [{"type": t} for t in case.objects.values()]
    changes = [{"instance_id": lab, "type": t} for lab, t in case.objects.items()]
    return CaseReport(
        str(case.root),
        summarize(scores),
        summarize_flags(o.flag for o in outcomes),
        objects,
        per_type_table(types, changes, labelled),
        tuple(outcomes),
        case.has_labels,
        {
            "detect": params_to_dict(params),
            "run": {
                "min_changed_fraction": config.run.min_changed_fraction,
                "min_region_fraction": config.run.min_region_fraction,
            },
        },
    )
