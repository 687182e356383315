"""The ``server start|stop|status`` commands: one local Prefect server in the background."""

from __future__ import annotations

from typing import Annotated

import typer
from rich.markup import escape

from tumor3d.flows.cli.app import app, console
from tumor3d.flows.cli.errors import _HANDLED, _fail

server_app = typer.Typer(
    help="One local Prefect server in the background, used by every later command "
    "(fast repeated runs; the runs appear in its UI). State in $TUMOR3D_HOME "
    "(default ~/.tumor3d): server.json, server.log.",
    no_args_is_help=True,
)
app.add_typer(server_app, name="server")


@server_app.command("start")
def server_start(
    port: Annotated[
        int | None, typer.Option(min=1, max=65535, help="Port (default: a free one).")
    ] = None,
) -> None:
    """Start the background Prefect server (or report the one already running)."""
    from tumor3d.flows.server import start_server

    try:
        info, started = start_server(port=port)
    except _HANDLED as exc:
        raise _fail(exc) from None
    what = "started" if started else "already running"
    console.print(
        f"Prefect server {what}: pid {info.pid}, API {escape(info.api_url)}, "
        f"UI {escape(info.api_url.removesuffix('/api'))}, log {escape(info.log)}",
        soft_wrap=True,
    )


@server_app.command("stop")
def server_stop() -> None:
    """Stop the background Prefect server (a stale state file is removed)."""
    from tumor3d.flows.server import stop_server

    try:
        before = stop_server()
    except _HANDLED as exc:
        raise _fail(exc) from None
    if before.state in ("running", "unhealthy") and before.info is not None:
        console.print(f"stopped the Prefect server (pid {before.info.pid})")
    elif before.state == "stale":
        console.print(f"no server was running; removed the {escape(before.line)}", soft_wrap=True)
    else:
        console.print("no tumor3d Prefect server was running")


@server_app.command("status")
def server_status_cmd() -> None:
    """Say whether the background server runs, where, and whether it is healthy.

    Exit code 0 when it is running and healthy, 1 otherwise.
    """
    from tumor3d.flows.server import server_status

    status = server_status()
    console.print(escape(status.line), soft_wrap=True, highlight=False)
    raise typer.Exit(code=0 if status.state == "running" else 1)
