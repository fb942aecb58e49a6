"""Where the detector's errors lie on synthetic streets: a diagnostic for tuning rounds, not a
timing benchmark. Every view is detected as ``streetcd evaluate`` detects it (the same
neighbours, the street's own config), then two tables per street kind (the folder's name
without its seed) and for all streets together:

* **the truth**: per change type, its cared-for truth pixels by the class of the old surface
  behind them (``-`` for none), each with its recall: what a missed change stands in front
  of, or where a removed one stood;
* **the false pixels** (detected, not truth, not don't-care): the share within ``--near-px``
  of the truth (the outline) and, of the farther ones (false alarms), the share without an
  old surface, by the cue with the largest value there (eq. 5's ``C_p``, the colour or
  intensity check's ``weight · A_p``, the texture cue's ``weight · T_p``; ``none`` where all
  are below 0.3: pixels the graph cut and the outline took in around the evidence), and by
  old class.

    .venv/bin/python benchmarks/error_breakdown.py out/dev/12img-1280x720-80m-3px/*-s[0-3]
    .venv/bin/python benchmarks/error_breakdown.py STREET... --config OVERLAY --tag T

Streets come from ``benchmarks/validation_set.py`` (or ``streetcd synth``); unchanged twins
add only false pixels. ``--config`` lays a YAML of settings over each street's own, as
``validation_set.py --config`` does (written beside it as ``streetcd-<tag>.yaml``). It takes
as long as ``streetcd evaluate`` on the same streets (docs/TUNING.md, thirty-fourth round,
has the development set's tables).
"""

from __future__ import annotations

import argparse
import sys
from collections import Counter, defaultdict
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from validation_set import merged_config  # noqa: E402

from streetcd import classes  # noqa: E402
from streetcd.config import DetectParams, load_config  # noqa: E402
from streetcd.detect.cache import SurfaceCache  # noqa: E402
from streetcd.detect.chain import DetectionResult, detect_view  # noqa: E402
from streetcd.eval.evaluate import load_scene, view_inputs  # noqa: E402

CUE_FLOOR = 0.3  # below this on every cue, a false pixel is "none": taken in, not evidence
CUES = ("eq. 5", "colour", "texture", "none")


class Tally:
    """The counts of one group of streets."""

    def __init__(self) -> None:
        self.truth: dict[str, Counter[int]] = defaultdict(Counter)  # type → class → pixels
        self.found: dict[str, Counter[int]] = defaultdict(Counter)  # type → class → detected
        self.false: Counter[str] = Counter()  # "all", "near", "far", "far without surface"
        self.cue: Counter[str] = Counter()  # of the far ones
        self.cls: Counter[int] = Counter()  # of the far ones

    def add(self, other: Tally) -> None:
        for t in other.truth:
            self.truth[t].update(other.truth[t])
            self.found[t].update(other.found[t])
        self.false.update(other.false)
        self.cue.update(other.cue)
        self.cls.update(other.cls)


def views_of(
    folder: Path, overlay: Path | None, tag: str
) -> Iterator[tuple[DetectionResult, dict[str, np.ndarray], dict[int, str], DetectParams]]:
    """(result, truth rasters, instance id → change type, params) per view of a street,
    detected as ``streetcd evaluate`` detects it."""
    config = merged_config(folder, overlay, tag)
    params = load_config(config).detect
    scene = load_scene(folder)
    types = {c["instance_id"]: c["type"] for c in scene.manifest.get("changes", [])}
    surfaces = SurfaceCache()
    for v, image, nbs, truth in view_inputs(scene, scene.views, params):
        result = detect_view(image, v, nbs, scene.cloud, params, surfaces=surfaces)
        yield result, truth, types, params


def tally_view(
    result: DetectionResult,
    truth: dict[str, Any],
    types: dict[int, str],
    params: DetectParams,
    near_px: int,
) -> Tally:
    """One view's counts (module docstring)."""
    out = Tally()
    care = ~truth["dontcare"].astype(bool)
    gt = truth["mask"].astype(bool) & care
    mask, cls = result.mask.astype(bool), result.classes
    inst = truth["instances"]
    for i in np.unique(inst[gt]):
        pick = gt & (inst == i)
        name = types.get(int(i), "?")
        for c, n in zip(*np.unique(cls[pick], return_counts=True), strict=True):
            out.truth[name][int(c)] += int(n)
            out.found[name][int(c)] += int((pick & mask & (cls == c)).sum())
    false = mask & ~gt & care
    if not false.any():
        return out
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * near_px + 1, 2 * near_px + 1))
    near = cv2.dilate(gt.astype(np.uint8), disc) > 0
    far = false & ~near
    out.false.update(
        {
            "all": int(false.sum()),
            "near": int((false & near).sum()),
            "far": int(far.sum()),
            "far without surface": int((far & ~np.isfinite(result.depth)).sum()),
        }
    )
    zero = np.zeros(mask.shape, np.float32)
    cues = np.stack(
        [
            np.nan_to_num(result.raw_change),
            zero if result.appearance is None else params.appearance.weight * result.appearance,
            zero if result.texture is None else params.texture.weight * result.texture,
        ]
    )
    best = np.where(cues.max(axis=0) < CUE_FLOOR, 3, cues.argmax(axis=0))
    for k, n in zip(*np.unique(best[far], return_counts=True), strict=True):
        out.cue[CUES[int(k)]] += int(n)
    for c, n in zip(*np.unique(cls[far], return_counts=True), strict=True):
        out.cls[int(c)] += int(n)
    return out


def _name(code: int) -> str:
    return "-" if code == 0 else classes.NAMES.get(code, str(code))


def _pct(part: float, whole: float) -> str:
    return f"{100 * part / whole:.0f} %" if whole else "–"


def print_tally(title: str, t: Tally) -> None:
    print(f"\n### {title}\n")
    if not t.truth:
        print("No truth (unchanged streets only).")
    else:
        print("| change | truth px | recall | by what is behind: share (recall) |")
        print("| --- | --- | --- | --- |")
    for name in sorted(t.truth):
        total, found = sum(t.truth[name].values()), sum(t.found[name].values())
        parts = ", ".join(
            f"{_name(c)} {_pct(n, total)} ({t.found[name][c] / n:.2f})"
            for c, n in t.truth[name].most_common(5)
        )
        print(f"| {name} | {total} | {found / total:.2f} | {parts} |")
    f = t.false
    far = f["far"]
    print(
        f"\nFalse pixels {f['all']}: within the outline {_pct(f['near'], f['all'])}, farther"
        f" {_pct(far, f['all'])}; of those farther, without an old surface"
        f" {_pct(f['far without surface'], far)}; by cue "
        + ", ".join(f"{c} {_pct(t.cue[c], far)}" for c in CUES)
        + "; by old class "
        + ", ".join(f"{_name(c)} {_pct(n, far)}" for c, n in t.cls.most_common(6))
        + "."
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("streets", nargs="+", type=Path, help="street folders")
    ap.add_argument("--config", type=Path, help="YAML of settings laid over each street's own")
    ap.add_argument("--tag", default="breakdown", help="names the merged config file")
    ap.add_argument("--near-px", type=int, default=20, help="the outline's reach from the truth")
    args = ap.parse_args(argv)
    kinds: dict[str, Tally] = defaultdict(Tally)
    for folder in args.streets:
        if not (folder / "manifest.json").exists():
            print(f"{folder}: no manifest.json, not a street", file=sys.stderr)
            return 2
        kind = folder.name.removesuffix("-unchanged").rsplit("-s", 1)[0]
        for result, truth, types, params in views_of(folder, args.config, args.tag):
            kinds[kind].add(tally_view(result, truth, types, params, args.near_px))
        print(f"{folder.name}: done", file=sys.stderr, flush=True)
    everything = Tally()
    for kind in sorted(kinds):
        print_tally(kind, kinds[kind])
        everything.add(kinds[kind])
    if len(kinds) > 1:
        print_tally("all streets", everything)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
