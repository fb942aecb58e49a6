"""The ``streetcd`` command: a click group; each sub-command lives in its own module."""

from __future__ import annotations

import importlib

import click

from streetcd import __version__

# (module, command attribute). Each module imports its heavy dependencies lazily so that
# `streetcd --help` stays fast.
COMMANDS = [
    ("streetcd.cli.synth", "synth"),
    ("streetcd.cli.evaluate", "evaluate"),
    ("streetcd.cli.detect", "detect"),
    ("streetcd.cli.check", "check"),
    ("streetcd.cli.run", "run"),
    ("streetcd.cli.run", "demo"),
    ("streetcd.cli.main", "query"),
    ("streetcd.cli.review", "review"),
    ("streetcd.cli.report", "report"),
    ("streetcd.cli.serve", "serve"),
    ("streetcd.cli.ingest", "ingest"),
    ("streetcd.cli.ingest", "tiles"),
    ("streetcd.cli.verify", "verify"),
]


class LazyGroup(click.Group):
    """A group that imports a command's module only when that command runs (or when the
    group's help lists them all): `streetcd query` then never imports the detector, the
    generator or numba (1.2 s → the query's own imports; docs/BENCHMARKS.md)."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(attr for _, attr in COMMANDS)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        for module_name, attr in COMMANDS:
            if attr == cmd_name:
                command = getattr(importlib.import_module(module_name), attr)
                assert isinstance(command, click.Command)
                return command
        return None


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="streetcd")
def cli() -> None:
    """Find what changed on a street: an older MLS point cloud against newer posed images."""


@click.command(
    "query",
    add_help_option=False,
    context_settings={"ignore_unknown_options": True, "allow_extra_args": True},
)
@click.pass_context
def query(ctx: click.Context) -> None:
    """List the change objects of a change index (or its flagged views, --views), filtered by
    segment, box, date, score and review status. Opens the index read-only."""
    # the options are argparse's (streetcd.cli.query): `streetcd query` runs without click
    from streetcd.cli.query import main as query_main

    ctx.exit(query_main(ctx.args))


if __name__ == "__main__":  # `python -m streetcd.cli.main`; the installed program starts at
    cli()  # streetcd.cli.entry, which runs `query` without click
