"""Thin command line over the library. Progress bars live here, never in the library."""

import click

INDEX_HELP = "The change index (SQLite) a run wrote."


def index_option(help: str = INDEX_HELP):  # noqa: A002 - click's own keyword
    """The ``--index PATH`` option of the commands that read a change index."""
    return click.option(
        "--index", "index", required=True, type=click.Path(dir_okay=False), help=help
    )
