"""``streetcd ingest`` (an MLS archive into a zarr tile store) and ``streetcd tiles`` (its index).

Thin over :mod:`streetcd.store.tiles`; the progress bar lives here. ``ingest`` exits with status 1
when any file failed (the good files are still ingested and the failures recorded).
"""

from __future__ import annotations

import json
import os
import sys

import click

from streetcd.errors import StreetcdError


@click.command()
@click.option(
    "--archive",
    required=True,
    metavar="DIR_OR_GLOB",
    help="Directory (searched recursively), glob pattern or file of LAS/LAZ.",
)
@click.option(
    "--store",
    required=True,
    type=click.Path(),
    metavar="STORE.zarr",
    help="Tile store to create or update.",
)
@click.option(
    "--tile-size",
    default=50.0,
    show_default=True,
    type=float,
    help="Ground tile edge in metres (fixed when the store is created).",
)
@click.option(
    "--workers",
    default=min(4, os.cpu_count() or 1),
    show_default=True,
    type=int,
    help="Processes reading files in parallel.",
)
@click.option(
    "--reader",
    type=click.Choice(["laspy", "pdal"]),
    default="laspy",
    show_default=True,
    help="Point reader; pdal needs the optional PDAL install.",
)
@click.option(
    "--pipeline",
    type=click.Path(dir_okay=False),
    default=None,
    help="PDAL pipeline JSON applied to each file (with --reader pdal).",
)
@click.option(
    "--chunk-points",
    default=1_000_000,
    show_default=True,
    type=int,
    help="Points read per chunk (memory per worker scales with it).",
)
@click.option(
    "--prune",
    is_flag=True,
    help="Drop the points of files the store has but the archive no longer lists.",
)
@click.option(
    "--recheck",
    is_flag=True,
    help="Read and check every chunk of the files already in the store; ingest again those "
    "whose points are damaged (what `streetcd verify` reports).",
)
def ingest(
    archive: str,
    store: str,
    tile_size: float,
    workers: int,
    reader: str,
    pipeline: str | None,
    chunk_points: int,
    prune: bool,
    recheck: bool,
) -> None:
    """Stream an MLS archive (LAS/LAZ) into square ground tiles of a zarr tile store.

    Resumable: files already ingested (same size and mtime) are skipped. A file removed
    from the archive keeps its points unless --prune is given. One ingest at a time per
    store: a second one fails at once.
    """
    from rich.console import Console
    from rich.progress import (
        BarColumn,
        Progress,
        TaskProgressColumn,
        TextColumn,
        TimeRemainingColumn,
    )

    from streetcd.io.readers import get_reader
    from streetcd.store.ingest import ingest as run_ingest

    console = Console(stderr=True)
    try:
        point_reader = get_reader(reader, pipeline)
        with Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            TaskProgressColumn(),
            TextColumn("{task.fields[points]}"),
            TimeRemainingColumn(),
            console=console,
        ) as bar:
            job = bar.add_task("ingest (reading headers)", total=None, points="")

            def on_progress(done: int, total: int, name: str) -> None:
                bar.update(
                    job,
                    completed=done,
                    total=total,
                    description=f"ingest {name}",
                    points=f"{done:,}/{total:,} points",
                )

            result = run_ingest(
                archive,
                store,
                tile_size_m=tile_size,
                workers=workers,
                reader=point_reader,
                chunk_points=chunk_points,
                prune=prune,
                progress=on_progress,
                recheck=recheck,
            )
    except StreetcdError as exc:
        raise click.ClickException(str(exc)) from None
    rate = result.points / result.seconds if result.seconds > 0 else 0.0
    click.echo(
        f"{result.store}: {len(result.ingested)} files ingested "
        f"({result.points:,} points, {rate:,.0f} points/s), {len(result.skipped)} "
        f"already there, {len(result.failed)} failed; {result.tiles} tiles "
        f"in {result.seconds:.1f} s"
    )
    for path in result.pruned:
        click.echo(f"pruned (no longer in the archive): {path}")
    for path, message in result.failed.items():
        click.echo(
            f"failed: {message}" if path in message else f"failed: {path}: {message}", err=True
        )
    if result.failed:
        sys.exit(1)


@click.command()
@click.argument("store", type=click.Path(exists=True, file_okay=False))
@click.option("--json", "as_json", is_flag=True, help="Print the index as JSON.")
def tiles(store: str, as_json: bool) -> None:
    """Print the tile index of STORE: bounds, point count, classes and sources per tile."""
    from streetcd.store.tiles import TileStore

    try:
        ts = TileStore.open(store)
    except StreetcdError as exc:
        raise click.ClickException(str(exc)) from None
    if as_json:
        click.echo(json.dumps(ts.to_json(), indent=1))
        return
    from rich.console import Console
    from rich.table import Table

    from streetcd.classes import NAMES

    table = Table(
        title=f"{ts.path}  ({ts.crs}, {ts.tile_size_m:g} m tiles, "
        f"{len(ts)} tiles, {ts.point_count:,} points)"
    )
    for col in ("tile", "min x, y, z", "max x, y, z", "points", "classes", "sources"):
        table.add_column(col, justify="right" if col == "points" else "left")
    for tile in ts.tiles.values():  # (i, j) order
        top = sorted(tile.classes.items(), key=lambda kv: -kv[1])[:3]
        classes = ", ".join(f"{NAMES.get(c, c)} {n / tile.count:.0%}" for c, n in top)
        b = tile.bounds
        table.add_row(
            tile.id,
            f"{b[0]:.2f}, {b[1]:.2f}, {b[2]:.2f}",
            f"{b[3]:.2f}, {b[4]:.2f}, {b[5]:.2f}",
            f"{tile.count:,}",
            classes,
            str(len(tile.fragments)),
        )
    Console().print(table)
    bad = {p: r for p, r in ts.files.items() if r["status"] == "failed"}
    for p, r in bad.items():
        error = r.get("error", "")
        click.echo(f"failed file: {error}" if p in error else f"failed file: {p}: {error}")
