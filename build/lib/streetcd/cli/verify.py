"""``streetcd verify STORE``: read every chunk of a tile store and check it.

Thin over :func:`streetcd.store.verify.verify_store`; the progress bar lives here. One line
per problem (stdout), then a summary; exit status 0 when the store is sound, 1 with problems
(or when the store cannot be opened at all: one ``Error:`` line).
"""

from __future__ import annotations

import sys

import click

from streetcd.errors import StreetcdError


@click.command()
@click.argument("store", type=click.Path())
@click.option("--quiet", is_flag=True, help="No progress bar.")
def verify(store: str, quiet: bool) -> None:
    """Check STORE: every chunk's checksum, that no chunk is missing, each array's metadata
    against the store's manifest, and the tile index against the file records."""
    from rich.console import Console
    from rich.progress import BarColumn, Progress, TaskProgressColumn, TextColumn

    from streetcd.store.verify import verify_store

    console = Console(stderr=True)
    try:
        with Progress(
            TextColumn("{task.description}"),
            BarColumn(),
            TaskProgressColumn(),
            TextColumn("{task.fields[chunks]}"),
            console=console,
            disable=quiet,
        ) as bar:
            job = bar.add_task("verify", total=None, chunks="")

            def on_progress(done: int, total: int, name: str) -> None:
                bar.update(
                    job,
                    completed=done,
                    total=total,
                    description=f"verify {name}",
                    chunks=f"{done:,}/{total:,} chunks",
                )

            report = verify_store(store, progress=on_progress)
    except StreetcdError as exc:
        raise click.ClickException(str(exc)) from None
    for problem in report.problems:
        click.echo(f"problem: {problem}")
    failed = f", {report.failed_files} files recorded as failed at ingest" * bool(
        report.failed_files
    )
    click.echo(
        f"{report.store}: {report.sources} sources, {report.chunks:,} chunks, "
        f"{report.points:,} points checked: {len(report.problems)} problems{failed}"
    )
    if report.problems:
        sys.exit(1)
