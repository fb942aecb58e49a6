"""The VALIDATION set of docs/TUNING.md ("Protocol against over-fitting"): generate it (cached)
and score the detector on it once.

    .venv/bin/python benchmarks/validation_set.py                       # the whole set
    .venv/bin/python benchmarks/validation_set.py --kinds plain --seeds 10 --images 6 \\
        --size 960x540 --no-unchanged                                    # a quick look

The set: for the default street and every street kind of ``streetcd synth --kind``
(:data:`streetcd.synth.kinds.PRESETS`), seeds 10–13 with 3 px pose noise, plus one unchanged
street per kind (``--no-changes``, the first seed) to count false alarms. Streets are
generated once under ``out/validation/`` (the folder name holds every setting, so a cached
street is reused only for the same settings); ``streetcd evaluate --scene DIR --json
DIR/eval.json --no-baselines`` then runs on each, with ``--config DIR/streetcd.yaml`` where
the street was written with other class codes. Never tune on this set: it is for reporting.
``--out out/dev --seeds 0,1,2,3 --unchanged-seeds 0,2`` makes and scores the same kinds of
street for the DEVELOPMENT set instead (``--unchanged-seeds``: whose twins; the first seed by
default); ``--config FILE`` lays a YAML of settings over each street's own (an ablation:
the street's class map stays, the file's values win), and ``--tag NAME`` keeps each
street's result under ``eval-NAME.json`` so that two settings can be compared.

Printed: one markdown table (street, kappa, TP %, FP %, % pixels flagged, views flagged),
the mean and minimum kappa per kind, and one line over every street (mean and lowest kappa,
views flagged with a change and without). "views flagged" counts, of the views with a true change,
those the nightly run's rule would flag, and of the views without, the same; when
``evaluate --scene`` gives no per-view flags (its JSON has no ``flags``), it is estimated from
each view's flagged share against the rule's ``min_region_fraction`` (an upper bound: the
rule asks that much of one region) and marked "≤".
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "out" / "validation"
SEEDS = (10, 11, 12, 13)
STREETCD = Path(sys.executable).with_name("streetcd")


@dataclass(frozen=True)
class Street:
    """One street of the set: its kind, seed and whether it has changes."""

    kind: str
    seed: int
    changes: bool
    n_images: int
    size: tuple[int, int]
    length_m: float
    pose_noise_px: float

    @property
    def name(self) -> str:
        return f"{self.kind}-s{self.seed}" + ("" if self.changes else "-unchanged")

    def folder(self, root: Path) -> Path:
        w, h = self.size
        settings = f"{self.n_images}img-{w}x{h}-{self.length_m:g}m-{self.pose_noise_px:g}px"
        return root / settings / self.name


def _cpu_s() -> float:
    """CPU seconds of this process so far (all threads: numba renders on every core)."""
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def generate(street: Street, root: Path) -> tuple[Path, tuple[float, float] | None]:
    """The street's folder, generated unless cached; (wall, CPU) seconds taken (None when
    cached)."""
    from streetcd.synth import generate_street

    folder = street.folder(root)
    if (folder / "manifest.json").exists():
        return folder, None
    start, cpu = time.perf_counter(), _cpu_s()
    generate_street(
        folder,
        seed=street.seed,
        n_images=street.n_images,
        size=street.size,
        pose_noise_px=street.pose_noise_px,
        length_m=street.length_m,
        changes=street.changes,
        kind=street.kind,
    )
    return folder, (time.perf_counter() - start, _cpu_s() - cpu)


def evaluate(
    folder: Path, views: int | None, overlay: Path | None = None, tag: str = ""
) -> dict[str, Any]:
    """``streetcd evaluate`` on one street (with the street's own config, ``overlay``'s
    settings laid over it); its JSON, kept as ``eval[-tag].json``."""
    out = folder / (f"eval-{tag}.json" if tag else "eval.json")
    cmd = [str(STREETCD), "evaluate", "--scene", str(folder), "--json", str(out), "--no-baselines"]
    config = merged_config(folder, overlay, tag)
    if config is not None:
        cmd += ["--config", str(config)]
    if views is not None:
        cmd += ["--views", str(views)]
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        tail = (done.stderr or done.stdout).strip().splitlines()[-1:] or ["no output"]
        raise RuntimeError(f"{folder}: streetcd evaluate failed: {tail[0]}")
    return json.loads(out.read_text(encoding="utf-8"))


def _deep_merge(base: dict[str, Any], top: dict[str, Any]) -> dict[str, Any]:
    out = dict(base)
    for key, value in top.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = _deep_merge(out[key], value)
        else:
            out[key] = value
    return out


def merged_config(folder: Path, overlay: Path | None, tag: str) -> Path | None:
    """The config file for one street: its own ``streetcd.yaml`` (a class map), with
    ``overlay``'s values laid over it (written as ``streetcd-<tag>.yaml`` beside it); None
    when there is neither."""
    import yaml

    own = folder / "streetcd.yaml"
    if overlay is None:
        return own if own.exists() else None
    base = yaml.safe_load(own.read_text(encoding="utf-8")) if own.exists() else {}
    top = yaml.safe_load(overlay.read_text(encoding="utf-8")) or {}
    mine = ((base or {}).get("detect") or {}).get("classes")
    theirs = (top.get("detect") or {}).get("classes")
    if mine and theirs and theirs != mine:
        # a whole configs/default.yaml laid over an ASPRS-coded street takes its roles away
        print(
            f"warning: {overlay}'s detect.classes replaces {folder.name}'s own class map;"
            " an overlay should hold the changed settings only",
            file=sys.stderr,
        )
    path = folder / f"streetcd-{tag or 'overlay'}.yaml"
    path.write_text(yaml.safe_dump(_deep_merge(base or {}, top)), encoding="utf-8")
    return path


def view_flags(folder: Path, data: dict[str, Any]) -> tuple[str, str]:
    """("flagged/with change", "flagged/without") for one street, from the evaluation's
    per-view flags, or estimated (marked "≤") from each view's flagged share."""
    if "flags" in data:
        f = data["flags"]
        return (
            f"{f['changed_flagged']}/{f['changed_views']}",
            f"{f['unchanged_flagged']}/{f['unchanged_views']}",
        )
    from streetcd.config import load_config

    config = folder / "streetcd.yaml"
    try:
        rule = load_config(config if config.exists() else None).run
    except Exception:  # a class map the config loader does not know yet: the rule's defaults
        rule = load_config(None).run
    manifest = json.loads((folder / "manifest.json").read_text(encoding="utf-8"))
    changed = {v["name"]: bool(v["changed_instances"]) for v in manifest["views"]}
    counts = [0, 0, 0, 0]  # with change: flagged, all; without: flagged, all
    for v in data["per_view"]:
        share = (v["flagged"] or 0.0) / 100.0
        flagged = share > rule.min_changed_fraction and share >= rule.min_region_fraction
        k = 0 if changed.get(v["name"], False) else 2
        counts[k] += flagged
        counts[k + 1] += 1
    return f"≤{counts[0]}/{counts[1]}", f"≤{counts[2]}/{counts[3]}"


def _num(x: float | None, digits: int = 1) -> str:
    return "–" if x is None else f"{x:.{digits}f}"


def main(argv: list[str] | None = None) -> int:
    from streetcd.synth.kinds import PRESETS

    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", default=",".join(map(str, SEEDS)), help="e.g. 10,11,12,13")
    ap.add_argument("--kinds", default=",".join(PRESETS), help=f"of {', '.join(PRESETS)}")
    ap.add_argument("--images", type=int, default=24, help="images per street [24]")
    ap.add_argument("--size", default="1920x1080", help="image size WxH [1920x1080]")
    ap.add_argument("--length", type=float, default=150.0, help="street length, m [150]")
    ap.add_argument("--pose-noise-px", type=float, default=3.0, help="pose noise, px [3]")
    ap.add_argument("--views", type=int, help="evaluate only the first N views of a street")
    ap.add_argument("--no-unchanged", action="store_true", help="skip the unchanged streets")
    ap.add_argument(
        "--unchanged-seeds",
        help="seeds of the unchanged streets, e.g. 0,2 [the first of --seeds]",
    )
    ap.add_argument("--generate-only", action="store_true", help="generate, do not evaluate")
    ap.add_argument("--out", type=Path, default=OUT, help=f"cache folder [{OUT}]")
    ap.add_argument("--config", type=Path, help="YAML of settings laid over each street's own")
    ap.add_argument("--tag", default="", help="keep results as eval-TAG.json (with --config)")
    args = ap.parse_args(argv)

    kinds = [k.strip() for k in args.kinds.split(",") if k.strip()]
    unknown = [k for k in kinds if k not in PRESETS]
    if unknown:
        ap.error(f"--kinds: {unknown[0]!r} is not one of {', '.join(PRESETS)}")
    try:
        seeds = [int(s) for s in args.seeds.split(",") if s.strip()]
        twins = seeds[:1]
        if args.unchanged_seeds:
            twins = [int(s) for s in args.unchanged_seeds.split(",") if s.strip()]
        w, h = (int(x) for x in args.size.lower().split("x"))
    except ValueError:
        ap.error("--seeds and --unchanged-seeds take integers such as 10,11; --size WIDTHxHEIGHT")
    streets = []
    for kind in kinds:
        for seed in seeds:
            streets.append(
                Street(kind, seed, True, args.images, (w, h), args.length, args.pose_noise_px)
            )
        if not args.no_unchanged:
            streets.extend(  # the same pose noise: false alarms under registration error
                Street(kind, seed, False, args.images, (w, h), args.length, args.pose_noise_px)
                for seed in twins
            )

    rows, kappas = [], {k: [] for k in kinds}
    views = [0, 0, 0, 0]  # with a change: flagged, all; without: flagged, all
    for street in streets:
        folder, seconds = generate(street, args.out)
        took = (
            "cached" if seconds is None else "generated in {:.0f} s ({:.0f} s CPU)".format(*seconds)
        )
        print(f"{street.name}: {folder} ({took})", file=sys.stderr, flush=True)
        if args.generate_only:
            continue
        data = evaluate(folder, args.views, args.config, args.tag)
        o = data["overall"]
        with_change, without = view_flags(folder, data)
        for i, counts in ((0, with_change), (2, without)):
            flagged, total = counts.lstrip("≤").split("/")
            views[i] += int(flagged)
            views[i + 1] += int(total)
        if street.changes and o["kappa"] is not None:
            kappas[street.kind].append(o["kappa"])
        rows.append(
            "| "
            + " | ".join(
                [
                    street.name,
                    _num(o["kappa"], 3) if street.changes else "–",
                    _num(o["tp"]) if street.changes else "–",
                    _num(o["fp"]) if street.changes else "–",
                    _num(o["flagged"], 3) if not street.changes else "–",
                    f"{with_change} with change, {without} without",
                ]
            )
            + " |"
        )
    if args.generate_only:
        return 0
    print("| street | kappa | TP % | FP % | % pixels flagged (unchanged) | views flagged |")
    print("| --- | --- | --- | --- | --- | --- |")
    print("\n".join(rows))
    print()
    print("| kind | streets | mean kappa | min kappa |")
    print("| --- | --- | --- | --- |")
    for kind, ks in kappas.items():
        mean = _num(statistics.fmean(ks), 3) if ks else "–"
        print(f"| {kind} | {len(ks)} | {mean} | {_num(min(ks), 3) if ks else '–'} |")
    every = [k for ks in kappas.values() for k in ks]
    if every:
        print(
            f"\nStreets with changes: {len(every)}, mean kappa {statistics.fmean(every):.3f}"
            f" (lowest {min(every):.3f}); views flagged: with a change {_share(*views[:2])},"
            f" without {_share(*views[2:])}"
        )
    return 0


def _share(part: int, whole: int) -> str:
    return f"{part} of {whole}" + (f" ({100 * part / whole:.1f} %)" if whole else "")


if __name__ == "__main__":
    raise SystemExit(main())
