"""The ``streetcd`` program's entry point (``[project.scripts]``).

``streetcd query`` goes straight to :mod:`streetcd.cli.query`, which parses its own
arguments: neither click nor the other commands are imported for it, so a script that polls
the index pays for Python, SQLite and the query alone (docs/BENCHMARKS.md). Every other
command goes to the click group, :mod:`streetcd.cli.main`.
"""

from __future__ import annotations

import sys


def main() -> None:
    if sys.argv[1:2] == ["query"]:
        from streetcd.cli.query import main as query_main

        sys.exit(query_main(sys.argv[2:]))
    from streetcd.cli.main import cli

    cli()
