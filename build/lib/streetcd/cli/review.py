"""``streetcd review``: record an operator's decision on a change object in the index."""

from __future__ import annotations

import getpass
import json

import click

from streetcd.cli.options import index_option
from streetcd.errors import StreetcdError


@click.command("review")
@click.argument("object_id")
@index_option()
@click.option(
    "--status",
    required=True,
    type=click.Choice(["confirmed", "false-alarm", "false_alarm", "fixed"]),
    help="confirmed: a real change; false-alarm: not one; fixed: dealt with on the street.",
)
@click.option("--note", help="A note kept with the decision.")
@click.option("--who", help="Who decided (default: the login name).")
def review(index: str, object_id: str, status: str, note: str | None, who: str | None) -> None:
    """Record a decision on change object OBJECT_ID (an id `streetcd query` lists). A
    confirmed or dismissed change is not listed as awaiting review again, on later nights
    too, unless the street changes again there; a fixed one seen again is a new change."""
    from streetcd.store.objects import record_review

    try:
        stored = record_review(index, object_id, status, who=who or _login(), note=note)
    except StreetcdError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(json.dumps({"id": object_id, "review": stored}))


def _login() -> str:
    try:
        return getpass.getuser()
    except Exception:  # no login name (a container without USER): say so rather than fail
        return "unknown"
