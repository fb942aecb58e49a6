"""``streetcd run`` (the nightly flow once, with a progress bar) and ``streetcd demo``.

Both run the Prefect flow in ``flows/nightly.py`` (installed as ``streetcd_flows``), which runs
:func:`streetcd.run.night.run_night` with Prefect's tracking. Without ``PREFECT_API_URL`` Prefect starts
a temporary local server for the run (about 20 s). Prefect's own log lines are shown from
level WARNING (failed views, failed files) unless ``--verbose``; the progress bar and the
summary come from here.

``streetcd run`` checks its inputs first (:func:`streetcd.run.check.check_inputs`), before
Prefect or Dask start, and exits with a code a cron job can act on (README, "Exit codes"):
0 a good night, 2 a whole-input error (one line on stderr naming the file and field), 3 more
views failed than ``--max-failed`` allows. Its summary JSON goes to ``OUT/runs/``.

After the check, the night runs in a child process that cannot outlive the command
(:mod:`streetcd.run.supervise`): however ``streetcd run`` is killed (SIGKILL, SIGTERM,
Ctrl-C), Prefect's temporary server and the Dask LocalCluster go with it. The child is
``python -m streetcd.cli.run SPEC`` (:func:`child_main`); its output, lines and exit code
are the command's.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path
from typing import Any

import click

from streetcd.errors import StreetcdError


def quiet_prefect(verbose: bool = False) -> None:
    """Environment defaults for a readable Prefect run; call before importing prefect."""
    # Must happen before prefect is imported: it configures its logging on import.
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "INFO" if verbose else "WARNING")
    os.environ.setdefault("PREFECT_SERVER_LOGGING_LEVEL", "WARNING")
    # The temporary server gets 20 s by default, too little on a busy machine; and its
    # telemetry, offline, only logs errors.
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120")
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    # Prefect's handlers would also show the in-process Dask scheduler's INFO chatter; dask
    # reads this when distributed is first imported.
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "info" if verbose else "warning")


def run_flow(*, verbose: bool = False, **kwargs: Any) -> dict[str, Any]:
    """Run ``flows.nightly.nightly(**kwargs)`` with a rich progress bar; returns its summary."""
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    from streetcd.run.progress import progress_listener

    quiet_prefect(verbose)
    # after quiet_prefect: prefect reads its settings when it is first imported
    from streetcd_flows.nightly import nightly

    with Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("flagged {task.fields[flagged]}  failed {task.fields[failed]}"),
        TimeElapsedColumn(),
        transient=False,
    ) as bar:
        job = bar.add_task("starting (Prefect, Dask)", total=None, flagged=0, failed=0)
        counts: dict[str, Any] = {"flagged": 0, "failed": 0}

        def on_progress(event: str, payload: Any) -> None:
            if event == "planned":
                bar.update(
                    job,
                    description=f"run {payload.run_id}",
                    total=payload.n_todo,
                    failed=len(payload.failed_at_plan),
                )
                counts["failed"] = len(payload.failed_at_plan)
            elif event == "batch":
                counts["flagged"] += sum(r.flagged for r in payload)
                counts["failed"] += sum(r.status == "failed" for r in payload)
                bar.update(job, advance=len(payload), **counts)

        with progress_listener(on_progress):
            state = nightly(**kwargs, return_state=True)
    # A night with too many failed views ends Failed with its summary as data; a flow that
    # raised carries the exception instead.
    result = state.result(raise_on_failure=False)
    if isinstance(result, BaseException):
        raise result
    return dict(result)


def print_summary(summary: dict[str, Any], index: str) -> None:
    s = summary
    click.echo(
        f"run {s['run_id']}: {s['n_views']} views, {s['n_skipped']} already in the index, "
        f"{s['n_done']} detected, {s['n_flagged']} flagged, {s['n_failed']} failed "
        f"in {s['wall_s']:.1f} s (detector {s['detect_s']:.1f} s in total)"
    )
    for view, error in s["failures"]:
        click.echo(f"  failed {view}: {error}")
    if s["n_lost"]:
        click.echo(f"  {s['n_lost']} views lost with their batches; run again to finish them")
    still = s.get("still_failing") or []
    if still:
        since = min((when for _, _, when in still if when), default="an earlier run")
        click.echo(
            f"  {len(still)} views still failing since {since} (fix their inputs, or "
            "--retry-failed):"
        )
        for view, error, _ in still[:10]:
            click.echo(f"    {view}: {error}")
        if len(still) > 10:
            click.echo(f"    ... and {len(still) - 10} more (see the summary)")
    click.echo(f"index: {index}")
    if s.get("summary_path"):
        click.echo(f"summary: {s['summary_path']}")
    if s.get("exit_code"):
        click.echo(f"exit code {s['exit_code']}: more views failed than --max-failed allows")


def parse_max_failed(text: str) -> float:
    """``--max-failed``: a count ("5"), a fraction ("0.1") or a percentage ("10%")."""
    try:
        value = float(text[:-1]) / 100 if text.endswith("%") else float(text)
    except ValueError:
        value = -1.0
    if not (0 <= value < 1 or (value.is_integer() and not text.endswith("%"))):
        raise click.BadParameter(
            f"{text!r}: a whole count (5), a fraction below 1 (0.1) or a percentage below "
            "100 (10%)",
            param_hint="--max-failed",
        )
    return value


def input_error(exc: StreetcdError, out: str | None = None) -> click.exceptions.Exit:
    """Print a whole-input error as one line on stderr (and record it in OUT/runs/ where
    given); the Exit to raise, code 2."""
    click.echo(f"Error: {exc}", err=True)
    if out is not None:
        from streetcd.run.summary import utc_now, write_input_error

        write_input_error(out, exc, utc_now())
    from streetcd.run.summary import EXIT_INPUT

    return click.exceptions.Exit(EXIT_INPUT)


def check_first(
    images: str, poses: str, store: str, index: str, archive: str | None, config_file: str | None
) -> None:
    """``streetcd check`` before Prefect and Dask start: its notes to stderr (its warnings
    come from the flow's own check, in Prefect's log); StreetcdError on a whole-input
    error."""
    from streetcd.config import load_config
    from streetcd.run.check import check_inputs

    report = check_inputs(images, poses, store, index, load_config(config_file), archive=archive)
    for note in report.notes:
        click.echo(f"note: {note}", err=True)


def _default(path: str | None, out: str, name: str) -> str:
    return str(Path(path) if path else Path(out) / name)


@click.command("run")
@click.option(
    "--images",
    required=True,
    type=click.Path(exists=True, file_okay=False),
    help="Folder of the new images.",
)
@click.option(
    "--poses",
    required=True,
    type=click.Path(exists=True),
    help="Their poses: COLMAP images.txt/.bin (or its folder) or an OPK .csv.",
)
@click.option(
    "--store",
    required=True,
    type=click.Path(),
    help="Tile store (zarr) of the reference MLS cloud.",
)
@click.option(
    "--archive",
    type=click.Path(exists=True),
    help="LAS/LAZ folder: ingest new files into the store first.",
)
@click.option(
    "--index",
    "index",
    type=click.Path(dir_okay=False),
    help="Change index (default OUT/change_index.sqlite).",
)
@click.option(
    "--scheduler",
    envvar="STREETCD_SCHEDULER",
    help="Dask scheduler address (default: $STREETCD_SCHEDULER, else a local cluster).",
)
@click.option(
    "--workers",
    type=click.IntRange(min=1),
    help="Worker processes of the local cluster (overrides the config's run.workers, default 2).",
)
@click.option(
    "--out",
    default="streetcd-out",
    show_default=True,
    type=click.Path(file_okay=False),
    help="Folder for masks and overlays.",
)
@click.option(
    "--config",
    "--params",
    "config_file",
    type=click.Path(exists=True, dir_okay=False),
    help="Settings (YAML, configs/default.yaml layout: detect: and run:). Default: the defaults.",
)
@click.option(
    "--batch-size",
    type=click.IntRange(min=1),
    help="Views per Dask task (overrides the config's run.batch_size, default 8).",
)
@click.option("--retry-failed", is_flag=True, help="Process again views that failed before.")
@click.option(
    "--max-failed",
    help="Failed views allowed before exit code 3: a count (5), a fraction (0.1) or a "
    "percentage (10%). Default: the config's run.max_failed, 0 (any failure fails the night).",
)
@click.option("-v", "--verbose", is_flag=True, help="Show Prefect's INFO logs.")
def run(
    images: str,
    poses: str,
    store: str,
    archive: str | None,
    index: str | None,
    scheduler: str | None,
    workers: int | None,
    out: str,
    config_file: str | None,
    batch_size: int | None,
    retry_failed: bool,
    max_failed: str | None,
    verbose: bool,
) -> None:
    """Run the nightly flow once: check the inputs, ingest, plan segments, detect on Dask,
    publish. Exit codes: 0 a good night, 2 a whole-input error (nothing ran), 3 more views
    failed than --max-failed allows (summary: OUT/runs/latest.json)."""

    index = _default(index, out, "change_index.sqlite")
    limit = None if max_failed is None else parse_max_failed(max_failed)
    try:
        check_first(images, poses, store, index, archive, config_file)
    except StreetcdError as exc:
        raise input_error(exc, out) from None
    spec = {
        "images": images,
        "poses": poses,
        "store": store,
        "index": index,
        "out": out,
        "archive": archive,
        "scheduler": scheduler,
        "workers": workers,
        "config_file": config_file,
        "batch_size": batch_size,
        "retry_failed": retry_failed,
        "max_failed": limit,
        "verbose": verbose,
    }
    raise click.exceptions.Exit(supervised_night(spec))


def supervised_night(spec: dict[str, Any]) -> int:
    """:func:`night` in a supervised child whose process group (Prefect's temporary server,
    the LocalCluster) dies with this process, however it ends; its exit code."""
    from streetcd.run import supervise

    if not supervise.supported():  # Windows: no process groups; the night runs in here
        return night(spec)
    cmd = [sys.executable, "-m", "streetcd.cli.run", json.dumps(spec)]
    return supervise.run_supervised(cmd, child_environment())


def night(spec: dict[str, Any]) -> int:
    """The night after the check: :func:`run_flow` on ``spec`` (its keyword arguments) and
    the summary; returns the exit code (2 with its one line for a whole-input error)."""
    try:
        summary = run_flow(**spec)
    except StreetcdError as exc:
        return input_error(exc, spec["out"]).exit_code
    print_summary(summary, spec["index"])
    return int(summary["exit_code"])


def child_environment() -> dict[str, str]:
    """The environment of the supervised night: ours, plus the Prefect settings in force
    here where prefect is already loaded (a test's temporary server is a setting, not an
    environment variable; the command itself never loads prefect)."""
    env = dict(os.environ)
    if "prefect" in sys.modules:
        from streetcd_flows.environment import prefect_environment

        env.update(prefect_environment())
    return env


def child_main(spec_json: str) -> int:
    """``python -m streetcd.cli.run SPEC``: the supervised night of ``streetcd run``; SPEC
    is :func:`night`'s argument as JSON. Returns the exit code."""
    from streetcd.run.supervise import watch_supervisor

    watch_supervisor()  # first: from here on, this process's group dies with the command
    try:
        return night(json.loads(spec_json))
    except KeyboardInterrupt:  # Ctrl-C, forwarded by the supervisor
        click.echo("Aborted!", err=True)
        return 130


@click.command("demo")
@click.option(
    "--out",
    default="streetcd-demo",
    show_default=True,
    type=click.Path(file_okay=False),
    help="Folder for the city, store and results.",
)
@click.option("--streets", type=int, default=3, show_default=True)
@click.option("--images-per-street", type=int, default=8, show_default=True)
@click.option("--size", default="960x540", show_default=True, help="Image size WxH.")
@click.option("--seed", type=int, default=0, show_default=True)
@click.option("--workers", type=int, default=2, show_default=True)
@click.option("-v", "--verbose", is_flag=True, help="Show Prefect's INFO logs.")
def demo(
    out: str,
    streets: int,
    images_per_street: int,
    size: str,
    seed: int,
    workers: int,
    verbose: bool,
) -> None:
    """Generate a small synthetic city, ingest it, run the nightly flow, list what changed."""
    from streetcd.cli.query import run_query
    from streetcd.run.summary import EXIT_OK, EXIT_VIEWS_FAILED

    try:
        w, h = (int(x) for x in size.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"{size!r}: expected WxH, e.g. 960x540") from None
    root = Path(out)
    try:
        paths = prepare_demo(
            root, seed=seed, streets=streets, images_per_street=images_per_street, size=(w, h)
        )
    except StreetcdError as exc:
        raise click.ClickException(str(exc)) from None
    spec = {
        **paths,
        "archive": None,
        "scheduler": None,
        "workers": workers,
        "config_file": None,
        "batch_size": None,
        "retry_failed": False,
        "max_failed": None,
        "verbose": verbose,
    }
    # supervised as `streetcd run` is: a killed demo leaves no server or cluster behind
    code = supervised_night(spec)
    if code in (EXIT_OK, EXIT_VIEWS_FAILED):  # the night ran: list what it found
        click.echo("")
        click.echo(run_query(paths["index"], fmt="table"))
        click.echo(
            f"\nmore: streetcd query --index {paths['index']} --format geojson -o changes.geojson"
        )
    # the same code as `streetcd run` (3 when views failed), so a smoke test of a fresh
    # install that runs the demo sees a failed view
    raise click.exceptions.Exit(code)


def prepare_demo(
    root: Path, *, seed: int, streets: int, images_per_street: int, size: tuple[int, int]
) -> dict[str, str]:
    """Generate the synthetic city under ``root/city`` and ingest its cloud into
    ``root/store.zarr``; return the flow's path arguments."""
    from streetcd.store.ingest import ingest
    from streetcd.synth import generate_city

    t0 = time.perf_counter()
    city = root / "city"
    manifest = city / "manifest.json"
    if _same_city(manifest, seed, streets, images_per_street):
        click.echo(f"city: {manifest} (already there)")
    else:
        click.echo(
            f"generating a synthetic city: {streets} streets x {images_per_street} "
            f"images of {size[0]}x{size[1]} (seed {seed}) ..."
        )
        manifest = Path(
            generate_city(
                city, seed=seed, n_streets=streets, images_per_street=images_per_street, size=size
            )
        )
        click.echo(f"city: {manifest} ({time.perf_counter() - t0:.1f} s)")
    store = root / "store.zarr"
    result = ingest(manifest.parent / "cloud", store)
    click.echo(f"store: {store} ({result.tiles} tiles, {len(result.ingested)} file(s) ingested)")
    return {
        "images": str(manifest.parent / "images"),
        "poses": str(manifest.parent / "poses" / "poses_opk.csv"),
        "store": str(store),
        "index": str(root / "change_index.sqlite"),
        "out": str(root / "results"),
    }


def _same_city(manifest: Path, seed: int, streets: int, images_per_street: int) -> bool:
    """Whether ``manifest`` is a finished city made with these settings (reruns reuse it, and
    the flow then finds every view already in the index)."""
    try:
        m = json.loads(manifest.read_text(encoding="utf-8"))
        g = m["generator"]
        return (g["kind"], g["seed"], g["n_streets"], len(m["views"])) == (
            "city",
            seed,
            streets,
            streets * images_per_street,
        )
    except (OSError, ValueError, KeyError, TypeError):
        return False


if __name__ == "__main__":
    sys.exit(child_main(sys.argv[1]))
