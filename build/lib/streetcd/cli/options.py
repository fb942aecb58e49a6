"""Options the click commands share."""

import click

from streetcd.cli import INDEX_HELP


def index_option(help: str = INDEX_HELP):  # noqa: A002 - click's own keyword
    """The ``--index PATH`` option of the commands that read a change index."""
    return click.option(
        "--index", "index", required=True, type=click.Path(dir_okay=False), help=help
    )
