"""``streetcd serve``: the review page live, recording decisions into the index (see
:mod:`streetcd.report.server`)."""

from __future__ import annotations

import signal

import click

from streetcd.cli.options import index_option
from streetcd.errors import StreetcdError


@click.command("serve")
@index_option("The change index (SQLite) a run wrote; decisions are recorded into it.")
@click.option(
    "--host",
    default="127.0.0.1",
    show_default=True,
    help="Address to listen on; any other than loopback needs the token printed at start.",
)
@click.option("--port", type=int, default=8765, show_default=True, help="0: any free port.")
@click.option("--token", help="The token to require (default: made up when not on loopback).")
@click.option(
    "--run", "run_id", help="The run whose numbers and inputs to show (default: the latest)."
)
def serve(index: str, host: str, port: int, token: str | None, run_id: str | None) -> None:
    """Serve the review page of a change index; review decisions made in the page are
    recorded into the index. Ctrl-C stops it."""
    from streetcd.report.server import close_server, make_server

    try:
        server = make_server(index, host=host, port=port, token=token, run_id=run_id)
    except (StreetcdError, OSError) as exc:
        raise click.ClickException(str(exc)) from None
    r = server.site.result
    click.echo(f"{r.changes} change(s) over {r.views} view(s); pictures ready in {r.seconds:.1f} s")
    click.echo(f"review page: {server.url}  (Ctrl-C stops)")
    signal.signal(signal.SIGTERM, _stop)  # a service manager's stop cleans up like Ctrl-C
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        click.echo("stopped", err=True)
    finally:
        close_server(server)


def _stop(signum: int, frame: object) -> None:
    raise KeyboardInterrupt
