"""``streetcd report``: the night's review page as a static site (see
:mod:`streetcd.report.site`)."""

from __future__ import annotations

import click

from streetcd.cli.options import index_option
from streetcd.errors import StreetcdError


@click.command("report")
@index_option()
@click.option(
    "--out",
    required=True,
    type=click.Path(file_okay=False),
    help="Folder for the site: index.html, its assets, data.js and thumbnails.",
)
@click.option(
    "--run", "run_id", help="The run whose numbers and inputs to show (default: the latest)."
)
def report(index: str, out: str, run_id: str | None) -> None:
    """Write a static review page of a change index: open OUT/index.html in a browser,
    offline (nothing is fetched from outside)."""
    from streetcd.report.site import write_report

    try:
        result = write_report(index, out, run_id=run_id)
    except StreetcdError as exc:
        raise click.ClickException(str(exc)) from None
    for note in result.notes:
        click.echo(f"note: {note}", err=True)
    click.echo(
        f"wrote {result.page}: {result.changes} change(s) over {result.views} view(s), "
        f"{result.pictures} picture(s), in {result.seconds:.1f} s"
    )
