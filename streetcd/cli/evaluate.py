"""``streetcd evaluate``: score the detector on a synthetic scene (Tables 1 and 2 of the
paper, with the Fig. 10(d) baselines), on an annotated case (a real street: pooled scores, per
object, and which views the nightly run would flag), or sweep the registration error."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import click

from streetcd.errors import StreetcdError


def _num(x: float | None, digits: int = 1) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def _table1(console: Any, overall: dict, baselines: dict) -> None:
    from rich.table import Table

    t = Table(title="Table 1 — change detection results (pooled over views)")
    for col in ("method", "GDR (%)", "FDR (%)", "TP (%)", "FP (%)", "KC", "flagged (%)"):
        if col == "method":
            t.add_column(col, justify="left", no_wrap=True, min_width=22)
        else:
            t.add_column(col, justify="right")
    rows = [("proposed", overall), *baselines.items()]
    for name, r in rows:
        t.add_row(name, *_rates(r))
    console.print(t)


def _rates(r: dict) -> tuple[str, ...]:
    """The cells of Table 1's columns GDR, FDR, TP, FP, KC and flagged for one result row."""
    return (
        _num(r["gdr"]),
        _num(r["fdr"]),
        _num(r["tp"]),
        _num(r["fp"]),
        _num(r["kappa"], 3),
        _num(r["flagged"], 2),
    )


def _table2(console: Any, per_type: dict) -> None:
    from rich.table import Table

    t = Table(title="Table 2 — per object type (scene level)")
    for col in ("type", "NS", "NGT", "NCDC", "NFDC"):
        t.add_column(col, justify="left" if col == "type" else "right")
    tot = [0, 0, 0, 0]
    for name, r in per_type.items():
        vals = [r["ns"], r["ngt"], r["ncdc"], r["nfdc"]]
        tot = [a + b for a, b in zip(tot, vals, strict=True)]
        t.add_row(name, *map(str, vals))
    t.add_row("Total", *map(str, tot), style="bold")
    console.print(t)


def _progress(console: Any) -> Any:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeElapsedColumn

    return Progress(
        "[progress.description]{task.description}",
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=console,
        transient=True,
    )


def _write_json(path: Path | None, data: dict) -> None:
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(data, indent=2, allow_nan=False))
    tmp.replace(path)


@click.command("evaluate")
@click.option(
    "--scene",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    help="Synthetic scene folder (from `streetcd synth`).",
)
@click.option(
    "--case",
    "case",
    type=click.Path(exists=True, file_okay=False, path_type=Path),
    help="Annotated case folder: images/, sparse/ (poses), cloud/*.laz, gt/<stem>.mask.png, "
    "gt/<stem>.dontcare.png [, gt/<stem>.labels.png, case.json].",
)
@click.option(
    "--index",
    "index_path",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="With --scene or --case: score this change index (from `streetcd run` on the "
    "scene's or the case's images) instead of running the detector: flagged pixels on true "
    "changes and don't-care disturbances, change objects against the manifest's changes (a "
    "case's labelled objects), transients kept out.",
)
@click.option(
    "--json",
    "json_out",
    type=click.Path(dir_okay=False, path_type=Path),
    help="Write the results as JSON here.",
)
@click.option(
    "--config",
    "--params",
    "params_path",
    type=click.Path(exists=True, dir_okay=False, path_type=Path),
    help="Settings YAML (configs/default.yaml layout; its detect: block is used, and for "
    "--case its run: flag rule); default: the defaults.",
)
@click.option(
    "--views", "max_views", type=click.IntRange(min=1), help="Evaluate only the first N views."
)
@click.option("--no-baselines", is_flag=True, help="Skip the Fig. 10(d) baselines.")
@click.option(
    "--sweep-pose-noise",
    "sweep",
    help="Comma-separated pose noise levels in pixels, e.g. 0,1,3,5,10: generate "
    "one scene per level (same seed) and report kappa against each.",
)
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the sweep scenes.")
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False, path_type=Path),
    default=Path("out/eval-scenes"),
    show_default=True,
    help="Where the sweep's scenes are generated and cached.",
)
def evaluate(
    scene: Path | None,
    case: Path | None,
    index_path: Path | None,
    json_out: Path | None,
    params_path: Path | None,
    max_views: int | None,
    no_baselines: bool,
    sweep: str | None,
    seed: int,
    out_dir: Path,
) -> None:
    """Score the detector on a synthetic scene: Table 1 (GDR, FDR, TP, FP, kappa) with the
    paper's baselines, Table 2 per object type; on an annotated case (--case: the same rates,
    per object, and the views the nightly run's rule flags); or kappa against the
    registration error. With --scene or --case and --index: score a `streetcd run` index of
    the scene's or the case's images instead (flagged pixels on true changes and on
    don't-care disturbances, change objects against the manifest's changes or the case's
    labelled objects, transients kept out and why)."""
    from rich.console import Console

    from streetcd.config import load_config

    console = Console(stderr=False)
    if index_path is not None and scene is None and case is None:
        raise click.UsageError(
            "--index is scored against a synthetic scene or an annotated case: give --scene DIR"
            " or --case DIR"
        )
    if sum(x is not None for x in (scene, case, sweep)) != 1:
        raise click.UsageError(
            "give exactly one of --scene DIR, --case DIR or --sweep-pose-noise LEVELS"
        )
    try:
        if index_path is not None:
            _write_json(json_out, _run_index(console, scene, case, index_path))
            return
        config = load_config(params_path)
        params = config.detect
        if sweep is not None:
            data = _run_sweep(console, sweep, seed, out_dir, params, max_views)
        elif case is not None:
            data = _run_case(console, case, config, max_views)
        else:
            assert scene is not None
            data = _run_scene(console, scene, config, max_views, not no_baselines)
    except StreetcdError as exc:
        raise click.ClickException(str(exc)) from None
    _write_json(json_out, data)


def _run_scene(
    console: Any, scene: Path, config: Any, max_views: int | None, baselines: bool
) -> dict:
    from streetcd.eval.evaluate import evaluate_scene, load_scene

    params = config.detect

    n = len(load_scene(scene).views) if max_views is None else max_views
    progress = _progress(console)
    with progress:
        task = progress.add_task(f"evaluating {scene.name}", total=n)
        report = evaluate_scene(
            scene,
            params,
            max_views=max_views,
            baselines=baselines,
            progress=lambda name: progress.advance(task),
        )
    data = report.as_dict()
    _table1(console, data["overall"], data["baselines"])
    _table2(console, data["per_type"])
    data["flags"] = _scene_flags(report, config.run)
    f = data["flags"]
    console.print(
        f"views the run would flag: {f['changed_flagged']} of {f['changed_views']} with a true "
        f"change, {f['unchanged_flagged']} of {f['unchanged_views']} without"
    )
    console.print(f"{len(report.views)} views, {report.seconds_per_view:.2f} s per view")
    return data


def _run_index(console: Any, scene: Path | None, case: Path | None, index_path: Path) -> dict:
    """``--scene DIR --index INDEX`` (issue 17, item 5) or ``--case DIR --index INDEX``: score
    the index's change objects."""
    from rich.table import Table

    from streetcd.eval.objects import score_case_index, score_index

    if case is not None:
        data = score_case_index(case, index_path).as_dict()
    else:
        assert scene is not None
        data = score_index(scene, index_path).as_dict()
    px = data["pixels"]
    t = Table(title=f"Flagged pixels of {data['flagged_views']} flagged views")
    for col in ("pixels of", "pixels", "on true change (%)", "on don't-care (%)", "elsewhere"):
        t.add_column(col, justify="left" if col == "pixels of" else "right")
    for name, key in (
        ("all flagged", "flagged"),
        ("objects reported as changes", "reported"),
        ("objects kept out (transients)", "kept_out"),
    ):
        r = px[key]
        t.add_row(
            name,
            str(r["pixels"]),
            _num(r["on_change_pct"]),
            _num(r["on_dontcare_pct"]),
            str(r["elsewhere"]),
        )
    console.print(t)
    console.print(
        f"true-change pixels kept in reported objects: {_num(px['true_change_kept_pct'])} % of "
        f"those flagged; of the truth's: {_num(px['truth_flagged_pct'])} % flagged, "
        f"{_num(px['truth_reported_pct'])} % reported; flagged views with no pixel on a true "
        f"change: {data['flagged_views_without_change']} of {data['flagged_views']}"
    )
    v = data["views"]
    console.print(
        f"views the run flagged: {v['with_change_flagged']} of the {v['with_change']} with a "
        f"true change ({_num(v['with_change_flagged_pct'])} %), {v['without_change_flagged']} "
        f"of the {v['without_change']} without ({_num(v['without_change_flagged_pct'])} %)"
    )
    t = Table(title="Labelled objects of the case" if case else "Changes of the manifest")
    cols = ("id", "kind", "type", "truth px", "flagged px", "reported px", "objects", "kept out")
    for col in (*cols, "off by m"):
        t.add_column(col, justify="left" if col in ("kind", "type") else "right")
    for c in data["changes"]:
        t.add_row(
            str(c["instance_id"]),
            c["kind"],
            c["type"],
            str(c["truth_px"]),
            str(c["flagged_px"]),
            str(c["reported_px"]),
            str(len(c["objects"])),
            str(len(c["kept_out"])),
            _num(c["position_error_m"], 2),
        )
    console.print(t)
    console.print(
        "(objects: reported as changes and matching it; kept out: transients matching it; "
        "off by: how far its largest reported object's centroid lies from its box, "
        "horizontally, where the truth gives a box)"
    )
    console.print(
        f"change objects: {data['objects_reported']} reported, {data['objects_kept_out']} kept "
        f"out as transients, for {data['changes_total']} changes; found "
        f"{data['changes_found']} of {data['changes_total']}, {data['changes_one_object']} by "
        f"exactly one object; object precision {_num(data['object_precision_pct'])} %, "
        f"recall {_num(data['object_recall_pct'])} %"
    )
    err = data["position_error_m"]
    if err["measured"]:
        console.print(
            f"found changes placed off their box by a median {_num(err['median'], 2)} m, at "
            f"most {_num(err['max'], 2)} m ({err['measured']} measured)"
        )
    t = Table(title="Transients kept out, by reason")
    for col in ("reason", "objects", "pixels", "on true change"):
        t.add_column(col, justify="left" if col == "reason" else "right")
    for reason, r in sorted(data["transient_reasons"].items()):
        t.add_row(reason, str(r["objects"]), str(r["pixels"]), str(r["on_change"]))
    console.print(t)
    return data


def _scene_flags(report: Any, run: Any) -> dict[str, int]:
    """How many views with and without a true change the run's flag rule would flag."""
    from streetcd.run.worker import is_flagged

    out = dict.fromkeys(
        ("changed_views", "changed_flagged", "unchanged_views", "unchanged_flagged"), 0
    )
    for v in report.views:
        pixels = [px for px, _ in v.regions]
        scores = [sc for _, sc in v.regions]
        flagged = is_flagged(sum(pixels) / max(v.n_pixels, 1), pixels, v.n_pixels, run, scores)
        which = "changed" if v.true_change else "unchanged"
        out[f"{which}_views"] += 1
        out[f"{which}_flagged"] += int(flagged)
    return out


def _run_sweep(
    console: Any, sweep: str, seed: int, out_dir: Path, params: Any, max_views: int | None
) -> dict:
    from rich.table import Table

    from streetcd.eval.evaluate import sweep_pose_noise

    try:
        levels = [float(x) for x in sweep.split(",") if x.strip()]
    except ValueError:
        raise click.BadParameter(
            f"{sweep!r} is not a comma-separated list of numbers", param_hint="--sweep-pose-noise"
        ) from None
    progress = _progress(console)
    with progress:
        task = progress.add_task("pose-noise sweep", total=len(levels))

        def step(level: float, stage: str) -> None:
            if stage == "done":
                progress.advance(task)
            else:
                progress.update(task, description=f"{level:g} px: {stage}")

        points = sweep_pose_noise(
            levels, out_dir, params, seed=seed, max_views=max_views, progress=step
        )
    rows = [p.as_dict() for p in points]
    t = Table(title=f"Kappa against registration error (seed {seed})")
    for col in ("pose noise (px)", "KC", "GDR (%)", "FDR (%)", "TP (%)", "FP (%)"):
        t.add_column(col, justify="right")
    for r in rows:
        t.add_row(
            f"{r['pose_noise_px']:g}",
            _num(r["kappa"], 3),
            _num(r["gdr"]),
            _num(r["fdr"]),
            _num(r["tp"]),
            _num(r["fp"]),
        )
    console.print(t)
    return {"seed": seed, "sweep": rows}


def _run_case(console: Any, case: Path, config: Any, max_views: int | None) -> dict:
    from streetcd.eval.case import evaluate_case, load_case

    loaded = load_case(case)
    n = len(loaded.views) if max_views is None else min(len(loaded.views), max_views)
    progress = _progress(console)
    with progress:
        task = progress.add_task(f"evaluating {case.name}", total=n)
        report = evaluate_case(
            loaded, config, max_views=max_views, progress=lambda name: progress.advance(task)
        )
    data = report.as_dict()
    _case_tables(console, data, case.name)
    console.print(f"{len(report.views)} views, {report.seconds_per_view:.2f} s per view")
    return data


def _case_tables(console: Any, data: dict, name: str) -> None:
    from rich.table import Table

    o = data["overall"]
    t = Table(title=f"{name} — change detection results (pooled over {data['n_views']} views)")
    for col in ("GDR (%)", "FDR (%)", "TP (%)", "FP (%)", "KC", "flagged (%)"):
        t.add_column(col, justify="right")
    t.add_row(*_rates(o))
    console.print(t)
    if data["labelled"] and not data["objects"]:
        console.print("No labelled objects (gt/*.labels.png hold no label).")
    elif data["labelled"]:
        t = Table(title="Per object (labels; detected: covered >= 50 % in half its views)")
        for col in ("label", "type", "GT px", "found px", "recall (%)", "views det./counted"):
            t.add_column(col, justify="left" if col == "type" else "right")
        t.add_column("detected", justify="left")
        for ob in data["objects"]:
            t.add_row(
                str(ob["label"]),
                ob["type"],
                str(ob["gt_px"]),
                str(ob["found_px"]),
                _num(ob["recall_pct"]),
                f"{ob['views_detected']}/{ob['views_counted']}",
                "yes" if ob["detected"] else "no",
            )
        console.print(t)
    f = data["flags"]
    rule = data["params"]["run"]
    t = Table(
        title="Views the nightly run would flag",
        caption=f"min_region_fraction {rule['min_region_fraction']:g}, "
        f"min_changed_fraction {rule['min_changed_fraction']:g}",
    )
    t.add_column("", justify="left")
    t.add_column("flagged", justify="right")
    t.add_column("(%)", justify="right")
    t.add_row(
        "views with a true change",
        f"{f['changed_flagged']}/{f['changed_views']}",
        _num(f["changed_flagged_pct"]),
    )
    t.add_row(
        "views without change",
        f"{f['unchanged_flagged']}/{f['unchanged_views']}",
        _num(f["unchanged_flagged_pct"]),
    )
    t.add_row(
        "pixels flagged on views without change", "", _num(f["unchanged_pixels_flagged_pct"], 3)
    )
    t.add_row("flagged pixels on dontcare", "", _num(f["flagged_on_dontcare_pct"]))
    console.print(t)
    t = Table(title="Per view")
    cols = ("view", "GT px", "flagged by run", "detected px", "KC", "surface (%)", "evidence (%)")
    for col in (*cols, "raw change GT / rest"):
        t.add_column(col, justify="left" if col == "view" else "right")
    t.add_column("neighbours (baseline m, * unused)", justify="left")
    t.add_column("s", justify="right")
    for v in data["per_view"]:
        nbs = ", ".join(
            f"{Path(n['name']).stem} {n['baseline_m']:.2f}{'' if n['used'] else '*'}"
            for n in v["neighbours"]
        )
        t.add_row(
            v["name"],
            str(v["gt_px"]),
            "yes" if v["flagged_by_run"] else "no",
            str(v["detected_px"]),
            _num(v["kappa"], 3),
            _num(v["surface_pct"]),
            _num(v["evidence_pct"]),
            f"{_num(v['raw_change_truth'], 3)} / {_num(v['raw_change_rest'], 3)}",
            nbs if v["error"] is None else v["error"],
            _num(v["seconds"], 1),
        )
    console.print(t)
