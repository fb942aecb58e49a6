"""Evaluation on synthetic scenes: run the detector on every view, score it (paper §5, Table 1
and 2), score the paper's baselines (Fig. 10(d)) from the same intermediate rasters, and sweep
the registration error.

A scene is a folder written by :func:`streetcd.synth.generate_street` (layout in
docs/CONTRACTS.md). The detector sees only what a user would give it: the images, the
*written* (noisy) poses and the reference cloud; the truth folder is read only for scoring.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from streetcd.config import DetectParams, GraphCutParams, params_to_dict
from streetcd.detect.cache import SurfaceCache
from streetcd.detect.chain import DetectionResult, detect_view
from streetcd.detect.correlate import stretch_histogram
from streetcd.detect.graphcut import cut_changes, node_energy
from streetcd.detect.refine import refined_mask
from streetcd.detect.regions import cut_apart
from streetcd.errors import CorruptFileError, InputError, MissingInputError
from streetcd.eval.metrics import Summary, TypeRow, ViewScore, per_type_table, score_view, summarize
from streetcd.geometry.neighbours import select_neighbours
from streetcd.io.images import read_image
from streetcd.io.las import load_clouds
from streetcd.io.poses import read_poses
from streetcd.synth import generate_street
from streetcd.types import PointCloud, View

THRESHOLDS = (0.12, 0.2, 0.3)  # Fig. 10(d): thresholds on the raw change scaled to [0, 1]
# Fig. 10(d): graph cut with the similarity terms of eq. 8 switched on and off
ABLATIONS: dict[str, dict[str, bool]] = {
    "color_only": {"use_color": True, "use_depth": False, "use_class": False},
    "color_depth_class": {"use_color": True, "use_depth": True, "use_class": True},
}

Progress = Callable[[str], None]


# ---------------------------------------------------------------------------------------------
# Scene loading (I/O edge)


@dataclass(frozen=True)
class Scene:
    """A synthetic scene on disk: manifest, reference cloud, written poses."""

    root: Path
    manifest: dict[str, Any]
    cloud: PointCloud
    views: tuple[View, ...]

    def view_record(self, view: View) -> dict[str, Any]:
        for rec in self.manifest["views"]:
            if Path(rec["name"]).stem == view.stem or rec["name"] == view.name:
                return rec
        raise MissingInputError(f"{self.root / 'manifest.json'}: no entry for view {view.name!r}")


def read_mask(path: Path, dtype: type = bool) -> np.ndarray:
    """(H, W) mask as written by the synthetic scene: uint8 0/255 → bool, uint16 ids kept."""
    import cv2

    if not path.exists():
        raise MissingInputError(f"ground-truth file not found: {path}")
    a = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if a is None or a.ndim != 2:
        raise CorruptFileError(f"{path}: not a single-channel mask image")
    return a > 0 if dtype is bool else a.astype(dtype)


def load_scene(root: str | Path) -> Scene:
    """Read a synthetic scene folder: the cloud (all LAZ files in one local frame) and the
    written poses (COLMAP text, else the OPK CSV)."""
    root = Path(root)
    mpath = root / "manifest.json"
    if not mpath.exists():
        raise MissingInputError(f"{root}: not a synthetic scene (no manifest.json)")
    try:
        manifest = json.loads(mpath.read_text())
    except json.JSONDecodeError as exc:
        raise CorruptFileError(f"{mpath}: not valid JSON: {exc}") from None
    files = sorted((root / "cloud").glob("*.la[sz]"))
    if not files:
        raise MissingInputError(f"{root / 'cloud'}: no LAS/LAZ files")
    cloud = load_clouds(files)
    colmap = root / "poses" / "colmap"
    poses = read_poses(
        colmap if colmap.exists() else root / "poses" / "poses_opk.csv", image_dir=root / "images"
    )
    return Scene(root, manifest, cloud, poses.views)


# ---------------------------------------------------------------------------------------------
# Per-view evaluation


@dataclass(frozen=True)
class ViewOutcome:
    """Scores of one view: the method, each baseline, and the detector's time; whether the
    truth has a change outside dontcare, and the detection's regions as (pixels, score) of an
    image of ``n_pixels``, for the run's flag rule (:func:`streetcd.run.worker.is_flagged`)."""

    name: str
    score: ViewScore
    baselines: dict[str, ViewScore]
    seconds: float
    true_change: bool = False
    regions: tuple[tuple[int, float], ...] = ()
    n_pixels: int = 0


@dataclass(frozen=True)
class Report:
    """Table 1 (overall and baselines), Table 2 (per type), timing."""

    overall: Summary
    per_type: dict[str, TypeRow]
    baselines: dict[str, Summary]
    views: tuple[ViewOutcome, ...]
    scene: str = ""
    params: dict[str, Any] = field(default_factory=dict)

    @property
    def seconds_per_view(self) -> float:
        return float(np.mean([v.seconds for v in self.views])) if self.views else math.nan

    def as_dict(self) -> dict[str, Any]:
        """The JSON layout of ``streetcd evaluate --json``."""
        return {
            "scene": self.scene,
            "n_views": len(self.views),
            "overall": self.overall.as_dict(),
            "per_type": {
                t: {"ns": r.ns, "ngt": r.ngt, "ncdc": r.ncdc, "nfdc": r.nfdc}
                for t, r in self.per_type.items()
            },
            "seconds_per_view": self.seconds_per_view,
            "baselines": {k: s.as_dict() for k, s in self.baselines.items()},
            "per_view": [
                {
                    "name": v.name,
                    **summarize([v.score]).as_dict(),
                    "seconds": v.seconds,
                    "true_change": v.true_change,
                    "regions": [list(r) for r in v.regions],
                    "n_pixels": v.n_pixels,
                }
                for v in self.views
            ],
            "params": self.params,
        }


def threshold_baseline(raw_change: np.ndarray, threshold: float) -> np.ndarray:
    """Fig. 10(d) baseline: (H, W) bool, raw change C_p (scaled to [0, 1]) ≥ ``threshold``."""
    return np.asarray(raw_change) >= threshold


def _score(
    mask: np.ndarray,
    truth: dict[str, np.ndarray],
    classes_raster: np.ndarray | None,
) -> ViewScore:
    return score_view(
        mask, truth["mask"], truth["instances"], truth["dontcare"], class_raster=classes_raster
    )


def evaluate_view(
    image: np.ndarray,
    view: View,
    neighbours: Sequence[tuple[np.ndarray, View]],
    cloud: PointCloud,
    truth: dict[str, np.ndarray],
    params: DetectParams,
    baselines: bool = True,
    surfaces: SurfaceCache | None = None,
) -> ViewOutcome:
    """Detect changes in one view and score it and the baselines against ``truth``
    ({"mask", "instances", "dontcare"} (H, W) arrays). ``surfaces``: a cache shared by the
    views of a scene (the result is the same without one, only slower)."""
    t0 = time.perf_counter()
    result = detect_view(image, view, neighbours, cloud, params, surfaces=surfaces)
    seconds = time.perf_counter() - t0
    score = _score(result.mask, truth, result.classes)
    extra: dict[str, ViewScore] = {}
    if baselines:
        for t in THRESHOLDS:
            extra[f"threshold_{t}"] = _score(
                threshold_baseline(result.raw_change, t), truth, result.classes
            )
        for name, switches in ABLATIONS.items():
            gparams = replace(params.graphcut, **switches)
            mask = (
                result.mask
                if gparams == params.graphcut
                else regraphcut(image, result, params, gparams)
            )
            extra[name] = _score(mask, truth, result.classes)
        if result.appearance is not None:
            # thresholds on the fused change the detector's node energy sees, so the margin
            # of the graph cut is measured against the strongest threshold, not the paper's
            fused = np.maximum(
                result.raw_change, np.float32(params.appearance.weight) * result.appearance
            )
            for t in THRESHOLDS:
                extra[f"fused_threshold_{t}"] = _score(
                    threshold_baseline(fused, t), truth, result.classes
                )
            # the paper's method: the same raw change, cut without the reference-colour check
            # and left with the superpixel outlines (no streetcd.detect.refine)
            energy = node_energy(result.raw_change, params.graphcut.a, params.graphcut.b)
            mask = regraphcut(image, result, params, params.graphcut, energy=energy, refine=False)
            extra["paper_method"] = _score(mask, truth, result.classes)
    cared = truth["mask"].astype(bool) & ~truth["dontcare"].astype(bool)
    regions = tuple((int(r.pixels), round(float(r.score), 4)) for r in result.regions)
    return ViewOutcome(
        view.name, score, extra, seconds, bool(cared.any()), regions, int(result.mask.size)
    )


def regraphcut(
    image: np.ndarray,
    result: DetectionResult,
    params: DetectParams,
    gparams: GraphCutParams,
    energy: np.ndarray | None = None,
    refine: bool = True,
) -> np.ndarray:
    """The graph cut (eq. 6–9), the speckle filter and, with ``refine``, the detector's steps
    after them (the outline refinement of :mod:`streetcd.detect.refine` when
    ``params.refine.enabled``, then an old vehicle's changed pixels cut apart from the rest,
    :func:`~streetcd.detect.regions.cut_apart`) again on one view's node energy (or
    ``energy``), depth, classes and superpixels (reused: the switches of eq. 8 do not change
    them) with other graph-cut parameters; (H, W) bool mask. ``refine`` False: the paper's
    steps alone."""
    stretched = stretch_histogram(image, params.correlate.stretch_percentiles)
    mask = cut_changes(
        result.node_energy if energy is None else energy,
        stretched,
        result.depth,
        result.classes,
        gparams,
        labels=result.superpixels,
    ).mask
    if not refine:
        return mask
    mask = refined_mask(image, mask, replace(params, graphcut=gparams))
    return cut_apart(mask, result.classes, params.refine.apart_classes)


def view_truth(scene: Scene, rec: dict[str, Any]) -> dict[str, np.ndarray]:
    """The truth rasters of one view (its manifest record ``rec``): ``mask`` (H, W) bool,
    ``instances`` (H, W) uint16 change-instance ids (0 none), ``dontcare`` (H, W) bool."""
    root = scene.root
    return {
        "mask": read_mask(root / rec["mask"]),
        "instances": read_mask(root / rec["instances"], np.uint16),
        "dontcare": read_mask(root / rec["dontcare"]),
    }


def view_inputs(
    scene: Scene, views: Sequence[View], params: DetectParams
) -> Iterator[tuple[View, np.ndarray, list[tuple[np.ndarray, View]], dict[str, np.ndarray]]]:
    """Per view of ``views`` (in trajectory order): the view, its image, its neighbours
    (image, view) as ``streetcd evaluate`` picks them among all the scene's views, and its
    truth (:func:`view_truth`). An image is read once and kept while it is in the window
    of the view and its neighbours."""
    cache: dict[str, np.ndarray] = {}

    def image_of(v: View) -> np.ndarray:
        if v.name not in cache:
            path = v.image if v.image is not None else scene.root / "images" / v.name
            cache[v.name] = read_image(Path(path))
        return cache[v.name]

    for v in views:
        nbs = select_neighbours(
            v,
            [c for c in scene.views if c.name != v.name],
            n=params.correlate.n_neighbours,
            min_parallax_px=params.correlate.min_parallax_px,
        )
        keep = {v.name, *(n.name for n in nbs)}
        for name in list(cache):  # views come in trajectory order; drop what left the window
            if name not in keep:
                del cache[name]
        truth = view_truth(scene, scene.view_record(v))
        yield v, image_of(v), [(image_of(n), n) for n in nbs], truth


def evaluate_scene(
    root: str | Path,
    params: DetectParams | None = None,
    *,
    max_views: int | None = None,
    baselines: bool = True,
    progress: Progress | None = None,
) -> Report:
    """Run and score every view (or the first ``max_views``) of a synthetic scene
    (``params`` None: the paper's defaults)."""
    params = DetectParams() if params is None else params
    scene = load_scene(root)
    views = scene.views if max_views is None else scene.views[:max_views]
    if not views:
        raise InputError(f"{scene.root}: no views to evaluate")
    surfaces = SurfaceCache()  # each view's surface serves it and its neighbours
    outcomes = []
    for v, image, nbs, truth in view_inputs(scene, views, params):
        outcomes.append(
            evaluate_view(image, v, nbs, scene.cloud, truth, params, baselines, surfaces)
        )
        if progress is not None:
            progress(v.name)
    scores = [o.score for o in outcomes]
    base = {k: summarize(o.baselines[k] for o in outcomes) for k in outcomes[0].baselines}
    m = scene.manifest
    return Report(
        summarize(scores),
        per_type_table(m.get("objects", []), m.get("changes", []), scores),
        base,
        tuple(outcomes),
        str(scene.root),
        params_to_dict(params),
    )


# ---------------------------------------------------------------------------------------------
# Scenes on demand, cached


def ensure_scene(cache_dir: str | Path, **kwargs: Any) -> Path:
    """A synthetic street generated with ``kwargs`` under ``cache_dir``, reused when its
    manifest is already there (the folder name encodes the arguments)."""
    key = "-".join(f"{k}={_fmt(v)}" for k, v in sorted(kwargs.items())) or "default"
    out = Path(cache_dir) / key
    if not (out / "manifest.json").exists():
        generate_street(out, **kwargs)
    return out


def _fmt(v: Any) -> str:
    if isinstance(v, tuple | list):
        return "x".join(str(x) for x in v)
    return str(v)


@dataclass(frozen=True)
class SweepPoint:
    """One noise level of :func:`sweep_pose_noise`: the pooled scores of its scene."""

    pose_noise_px: float
    summary: Summary
    seconds_per_view: float
    scene: Path

    def as_dict(self) -> dict[str, Any]:
        return {
            "pose_noise_px": self.pose_noise_px,
            **self.summary.as_dict(),
            "seconds_per_view": self.seconds_per_view,
            "scene": str(self.scene),
        }


# (noise level in px, stage: "generating", "detecting" or "done")
SweepProgress = Callable[[float, str], None]


def sweep_pose_noise(
    levels: Iterable[float],
    cache_dir: str | Path,
    params: DetectParams,
    *,
    seed: int = 0,
    scene_kwargs: dict[str, Any] | None = None,
    max_views: int | None = None,
    progress: SweepProgress | None = None,
) -> list[SweepPoint]:
    """Kappa (and the other rates) against the registration error: one scene per noise level
    (pixels RMS, generated under ``cache_dir`` or reused, see :func:`ensure_scene`), all from
    the same seed, so only the written poses differ; scored without the baselines."""
    points = []
    for level in map(float, levels):
        if progress is not None:
            progress(level, "generating")
        root = ensure_scene(cache_dir, seed=seed, pose_noise_px=level, **(scene_kwargs or {}))
        if progress is not None:
            progress(level, "detecting")
        rep = evaluate_scene(root, params, max_views=max_views, baselines=False)
        points.append(SweepPoint(level, rep.overall, rep.seconds_per_view, root))
        if progress is not None:
            progress(level, "done")
    return points
