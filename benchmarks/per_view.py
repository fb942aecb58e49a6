"""Per-view detector time, step by step, and peak memory, on ONE core.

    .venv/bin/python benchmarks/per_view.py [--sizes 1920x1080,4000x3000] [--repeat 3]
        [--kind sparse] [--config FILE]

For each image size a small synthetic street (6 images, 6.25 m apart as on the quick
tour's street; ``--kind``: a street kind of
``streetcd synth --kind``, e.g. ``sparse`` for a tenth of the points) is generated once and
cached under ``out/bench-scenes``; one middle view with 3 neighbours is detected ``--repeat`` times after a
warm-up (numba compilation, caches), and the median of every step is printed:

* project + z-buffer (eq. 1–3) and surface (triangulation, rasters, the near points' fill)
  for the view and its 3 neighbours, as :func:`streetcd.detect.chain.detect_view` does them;
* correlate: histogram stretching of the view, the neighbours' colour envelopes, their
  registration shifts (:mod:`streetcd.detect.align`) and the raw change (eq. 4–5), with the
  pairwise levels and the near-depth hypothesis (:mod:`streetcd.detect.silhouette`);
* appearance: the reference-colour check (:mod:`streetcd.detect.appearance`);
* texture: the texture cue (:mod:`streetcd.detect.texture`), when ``texture.enabled``;
* superpixels (class-aware SLIC, eq. 10–11) and graph cut (eq. 6–9, speckle filter);
* refine: the regions' pixel outlines by colour (:mod:`streetcd.detect.refine`) and the speckle
  filter again;
* regions: the mask cut apart where old vehicles' pixels meet others', its 8-connected
  regions located in 3D (:mod:`streetcd.detect.regions`) and how far in front of the old
  surface each stands (:mod:`streetcd.detect.locate`);
* total: :func:`detect_view` end to end (its own run, not the sum), every surface built;
* total_in_a_run: the same call as the flow makes it, with the neighbours' surfaces already
  built (each image's surface is built once per run and kept while its segment is detected,
  :class:`streetcd.detect.cache.SurfaceCache`), so only the view's own surface is built.

Baseline in the same run: scikit-image ``slic`` on the full-resolution image with the same
number of segments, against the detector's superpixel path (SLIC at a working resolution).
Goal: ≤ 0.6 s per 2 MP view, ≤ 3 s per 12 MP view, ≤ 2 GB peak; both totals are held
against it.

Each size runs in a fresh child process with the malloc settings of a flow's workers
(:data:`streetcd.run.cluster.WORKER_MALLOC_ENV`). Peak memory is measured there:
``ru_maxrss`` after loading the scene (cloud and 6 images), after the first detection (every
surface built: the goal's number), and at the end (the benchmark's own step-by-step run
holds every surface at once, and the in-a-run cache four).
"""

from __future__ import annotations

import os

for _var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ[_var] = "1"  # before numpy / numba are imported

import argparse  # noqa: E402
import json  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from dataclasses import replace  # noqa: E402
from pathlib import Path  # noqa: E402

import cv2  # noqa: E402
import numpy as np  # noqa: E402

cv2.setNumThreads(1)

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "out" / "bench-scenes"
STEPS = (
    "project_zbuffer",
    "surface",
    "correlate",
    "superpixels",
    "appearance",
    "texture",
    "graph_cut",
    "refine",
    "regions",
    "sum_of_steps",
    "total",
    "total_in_a_run",
)
N_STEPS = 9  # the per-step rows above sum_of_steps
TIMED_RUNS = ("total", "total_in_a_run")  # whole detect_view calls, timed on their own
N_IMAGES = 6  # enough that the middle view has 3 overlapping neighbours (4 gave it 2)
# The quick tour's spacing (24 images over 150 m): 6 images over the generator's default
# 150 m were 30 m apart, where the texture cue found almost no pixel to compare and
# skipped most of its work, so the benchmark's view was cheaper than the street's
# (docs/BENCHMARKS.md, 2026-11-29).
LENGTH_M = N_IMAGES * 150.0 / 24


def scene_for(size: tuple[int, int], kind: str | None = None) -> Path:
    from streetcd.eval.evaluate import ensure_scene

    extra = {} if kind is None else {"kind": kind}
    return ensure_scene(SCENES, seed=0, n_images=N_IMAGES, size=size, length_m=LENGTH_M, **extra)


def _fresh_cloud(scene):
    """The scene's cloud with colour and class arrays no surface cache has seen, so that its
    colours are converted and its classes read as roles within the timed call, as for a
    freshly cropped cloud."""
    rgb = scene.cloud.rgb
    return replace(
        scene.cloud,
        rgb=None if rgb is None else rgb.copy(),
        classification=scene.cloud.classification.copy(),
    )


def _setup(size: tuple[int, int], kind: str | None = None, config: str | None = None):
    from streetcd.config import load_config
    from streetcd.eval.evaluate import load_scene
    from streetcd.geometry.neighbours import select_neighbours
    from streetcd.io.images import read_image

    scene = load_scene(scene_for(size, kind))
    default = ROOT / "configs" / "default.yaml"
    params = load_config(config or (default if default.exists() else None)).detect
    view = scene.views[len(scene.views) // 2]
    nbs = select_neighbours(view, scene.views, n=3)
    if len(nbs) != 3:
        raise SystemExit(f"{view.name} has {len(nbs)} overlapping neighbours, not 3")
    image = read_image(Path(view.image))
    neighbours = [(read_image(Path(v.image)), v) for v in nbs]
    return scene, params, view, image, neighbours


def steps_once(scene, params, view, image, neighbours) -> dict[str, float]:
    """One detection split into the paper's steps (the same calls as detect_view: the
    metric z-buffer of surface_for_view, the neighbours' uint8 colour envelopes)."""
    from streetcd.detect.chain import (
        _aligned,
        _greys,
        _located,
        _locating,
        _neighbour,
        _outline_grey,
        _raw_change_at_cell_scale,
        _texture,
        _with_near_hypothesis,
        fuse_appearance,
        gate_second_smallest,
        reference_kind,
    )
    from streetcd.detect.correlate import stretch_lut
    from streetcd.detect.graphcut import cut_changes, node_energy, superpixels
    from streetcd.detect.refine import refined_mask
    from streetcd.detect.regions import changed_regions, cut_apart
    from streetcd.detect.roles import infers, road_told
    from streetcd.detect.surface import (
        _point_spacing,
        _zbuffer_params_for,
        fill_from_points,
        reach_px,
        rgb8,
        view_surface,
        zbuffer_keep,
    )
    from streetcd.detect.zbuffer import project_cloud

    t: dict[str, float] = dict.fromkeys(STEPS[:N_STEPS], 0.0)
    cloud = scene.cloud
    colours = None if cloud.rgb is None else rgb8(cloud.rgb)
    surfaces = []
    for img, v in [(image, view), *neighbours]:
        local = v.local(cloud.origin)
        intr = local.intrinsics
        zparams = _zbuffer_params_for(params.zbuffer, intr.width)
        t0 = time.perf_counter()
        pts = project_cloud(cloud.xyz, cloud.classification, intr, local.pose, params.max_range_m)
        if len(pts) == 0:
            continue  # detect_view leaves out a neighbour that sees no point
        focal = 0.5 * (intr.fx + intr.fy)
        # the cloud's own spacing per class, as surface_for_view measures and passes it
        spacing = _point_spacing(cloud.xyz, cloud.classification, pts, params)
        keep = zbuffer_keep(pts, img, zparams, focal, spacing)
        kept = pts.take(keep)
        t1 = time.perf_counter()
        kept_colours = None if colours is None else colours[kept.index]
        kept_spacing = None if spacing is None else spacing[keep]
        surf = view_surface(
            kept.uv,
            kept.depth,
            kept.classes,
            img.shape[:2],
            params.surface,
            cell_px=zparams.block_window_px,
            colours=kept_colours,
            spacing=None if kept_spacing is None else (kept_spacing, focal),
        )
        if params.surface.point_fill_classes and not infers(  # as view_surface_of
            cloud.classification, params.classes
        ):
            reach = reach_px(kept.depth, zparams, focal, kept_spacing)
            surf = fill_from_points(surf, kept, reach, params.surface, kept_colours)
        t2 = time.perf_counter()
        t["project_zbuffer"] += t1 - t0
        t["surface"] += t2 - t1
        surfaces.append((surf, local, img))
    t0 = time.perf_counter()
    pct = params.correlate.stretch_percentiles
    view_lut = stretch_lut(image, pct)
    stretched = cv2.LUT(image, view_lut)
    surf, local, _ = surfaces[0]
    nbs = [
        _neighbour(img, s, loc, surf, local, view_lut, image, params)
        for s, loc, img in surfaces[1:]
    ]
    seen = [
        (img, s.depth, loc.intrinsics, loc.pose, nb.holes)
        for (s, loc, img), nb in zip(surfaces[1:], nbs, strict=True)
    ]
    greys = _greys(image, seen) if nbs else None
    working = None
    if params.correlate.align_shift_px > 0 and greys is not None:
        nbs, working = _aligned(nbs, greys, surf, local, params)  # the registration shifts
    kind = reference_kind(scene.cloud, params) if surf.colour is not None else None
    gated = kind == "colour" and params.correlate.second_smallest_gate > 0
    change, _, minimum = _raw_change_at_cell_scale(  # as detect_view
        stretched, surf.depth, surf.classes, local, nbs, params, keep_minimum=gated
    )
    if minimum is not None:
        change = gate_second_smallest(change, minimum, image, surf, local, params)
    if params.correlate.silhouette_margin_m > 0 and nbs:
        grey = _outline_grey(image, view_lut, params)
        change = _with_near_hypothesis(change, stretched, surf, local, nbs, params, grey)
    t1 = time.perf_counter()
    labels = superpixels(stretched, surf.classes, params.graphcut)
    t2 = time.perf_counter()
    ground = kind == "colour" and road_told(cloud.classification, params.classes)
    inferred = infers(cloud.classification, params.classes)
    change, _ = fuse_appearance(
        image, surf, change, local, params, ground=ground, inferred=inferred
    )
    t3 = time.perf_counter()
    if params.texture.enabled and greys is not None:
        coloured = params.appearance.enabled and kind == "colour"  # as detect_view
        texture = _texture(*greys, surf, local, params, working, coloured)
        change = np.maximum(change, np.float32(params.texture.weight) * texture)
    t4 = time.perf_counter()
    energy = node_energy(change, params.graphcut.a, params.graphcut.b)
    cut = cut_changes(energy, stretched, surf.depth, surf.classes, params.graphcut, labels=labels)
    t5 = time.perf_counter()
    mask = refined_mask(image, cut.mask, params)
    t6 = time.perf_counter()
    mask = cut_apart(mask, surf.classes, params.refine.apart_classes)
    region_labels, regions = changed_regions(
        mask, energy, surf.depth, surf.classes, local.intrinsics, local.pose
    )
    if regions and params.locate.enabled:
        locating = _locating(image, surf, local, seen, params)
        if locating is not None:
            _located(regions, region_labels, locating, local, params)
    t7 = time.perf_counter()
    t["correlate"] = t1 - t0
    t["superpixels"] = t2 - t1
    t["appearance"] = t3 - t2
    t["texture"] = t4 - t3
    t["graph_cut"] = t5 - t4
    t["refine"] = t6 - t5
    t["regions"] = t7 - t6
    t["sum_of_steps"] = sum(t[s] for s in STEPS[:N_STEPS])
    return t


def detect_in_a_run(scene, params, view, image, neighbours) -> float:
    """Seconds of :func:`detect_view` as the flow runs it: every image's surface is built
    once and kept (:class:`streetcd.detect.cache.SurfaceCache`) while its segment is detected, so
    a view whose neighbours came before or were needed by an earlier view builds only its
    own surface. The neighbours' surfaces are put in a fresh cache first, untimed."""
    from streetcd.detect.cache import SurfaceCache
    from streetcd.detect.chain import detect_view, view_surface_of

    cloud = _fresh_cloud(scene)
    cache = SurfaceCache()
    for img, v in neighbours:
        view_surface_of(img, v.local(cloud.origin), cloud, params, cache)
    t0 = time.perf_counter()
    detect_view(image, view, neighbours, cloud, params, surfaces=cache)
    return time.perf_counter() - t0


def baseline_slic_once(image: np.ndarray, params) -> float:
    """scikit-image SLIC at full resolution, as many segments as the detector's cells."""
    from skimage.segmentation import slic

    from streetcd.config import scale_px

    h, w = image.shape[:2]
    cell = scale_px(params.graphcut.superpixel_cell_px, w, minimum=2.0)
    t0 = time.perf_counter()
    slic(
        image,
        n_segments=max(1, round(h * w / cell**2)),
        compactness=params.graphcut.compactness,
        start_label=0,
    )
    return time.perf_counter() - t0


def run_size(
    size: tuple[int, int], repeat: int, kind: str | None = None, config: str | None = None
) -> dict:
    """Timings (medians) and memory of one size; run in a fresh process."""
    from streetcd.detect.chain import detect_view

    scene, params, view, image, neighbours = _setup(size, kind, config)
    rss_loaded = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024  # MiB on Linux
    # surfaces=None: build every surface afresh, as a worker does for a view it has not seen
    detect_view(image, view, neighbours, scene.cloud, params, surfaces=None)  # warm-up
    rss_detect = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    steps_once(scene, params, view, image, neighbours)
    runs = [steps_once(scene, params, view, image, neighbours) for _ in range(repeat)]
    totals = []
    for _ in range(repeat):
        cloud = _fresh_cloud(scene)
        t0 = time.perf_counter()
        detect_view(image, view, neighbours, cloud, params, surfaces=None)
        totals.append(time.perf_counter() - t0)
    in_run = [detect_in_a_run(scene, params, view, image, neighbours) for _ in range(repeat)]
    out = {s: statistics.median(r[s] for r in runs) for s in STEPS if s not in TIMED_RUNS}
    out["total"] = statistics.median(totals)
    out["total_in_a_run"] = statistics.median(in_run)
    baseline_slic_once(image, params)
    out["baseline_skimage_slic_full_res"] = statistics.median(
        baseline_slic_once(image, params) for _ in range(repeat)
    )
    return {
        "size": f"{size[0]}x{size[1]}",
        "megapixels": size[0] * size[1] / 1e6,
        "points": len(scene.cloud),
        "seconds": out,
        "rss_loaded_mib": rss_loaded,
        "rss_peak_mib": rss_detect,  # the first detect_view, before anything else ran
        # the benchmark's own later work holds more at once (steps_once keeps every surface,
        # the in-a-run cache four), so this is not the detector's
        "rss_end_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="1920x1080,4000x3000")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--kind", default=None, help="a street kind of streetcd synth --kind")
    ap.add_argument("--config", default=None, help="settings instead of configs/default.yaml")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    from streetcd.run.cluster import WORKER_MALLOC_ENV

    if args.child:
        w, h = map(int, args.child.split("x"))
        print(json.dumps(run_size((w, h), args.repeat, args.kind, args.config)))
        return
    results = []
    for spec in args.sizes.split(","):
        w, h = map(int, spec.split("x"))
        scene_for((w, h), args.kind)  # generate outside the measured child
        extra = [] if args.kind is None else ["--kind", args.kind]
        extra += [] if args.config is None else ["--config", str(Path(args.config).resolve())]
        proc = subprocess.run(
            [sys.executable, __file__, "--child", spec, "--repeat", str(args.repeat), *extra],
            capture_output=True,
            text=True,
            check=False,
            env={**os.environ, **WORKER_MALLOC_ENV},  # glibc's malloc as a flow worker has it
        )
        if proc.returncode != 0:
            sys.exit(f"benchmark at {spec} failed:\n{proc.stderr}")
        results.append(json.loads(proc.stdout.strip().splitlines()[-1]))
    print_table(results)


def print_table(results: list[dict]) -> None:
    names = [*STEPS, "baseline_skimage_slic_full_res"]
    head = f"{'step (median s, 1 core)':<34}" + "".join(f"{r['size']:>14}" for r in results)
    print(head)
    print("-" * len(head))
    for name in names:
        print(f"{name:<34}" + "".join(f"{r['seconds'][name]:>14.3f}" for r in results))
    print(f"{'points in cloud':<34}" + "".join(f"{r['points']:>14d}" for r in results))
    print(
        f"{'peak RSS after scene load (MiB)':<34}"
        + "".join(f"{r['rss_loaded_mib']:>14.0f}" for r in results)
    )
    print(
        f"{'peak RSS incl. one detection':<34}"
        + "".join(f"{r['rss_peak_mib']:>14.0f}" for r in results)
    )
    print(
        f"{'peak RSS, whole benchmark (MiB)':<34}"
        + "".join(f"{r['rss_end_mib']:>14.0f}" for r in results)
    )
    goals = {"1920x1080": 0.6, "4000x3000": 3.0}
    for r in results:
        goal = goals.get(r["size"])
        if goal is None:
            continue
        sec = r["seconds"]
        for name, what in (
            ("total", "one view alone (its own and 3 neighbour surfaces built)"),
            ("total_in_a_run", "a view in a run (neighbour surfaces already built)"),
        ):
            ok = sec[name] <= goal and r["rss_peak_mib"] <= 2048
            print(
                f"{r['size']}, {what}: {sec[name]:.2f} s (goal ≤ {goal} s), "
                f"peak {r['rss_peak_mib']:.0f} MiB (goal ≤ 2048): "
                f"{'meets' if ok else 'MISSES'} the goal"
            )


if __name__ == "__main__":
    main()
