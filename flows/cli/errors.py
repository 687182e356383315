"""Exit codes and errors: every error that ends a command is one line and an exit code."""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import typer
from rich.markup import escape

from tumor3d.errors import Tumor3DError
from tumor3d.flows.cli.app import console, err_console
from tumor3d.flows.exit_codes import (  # noqa: F401  (the command line's names for them)
    EXIT_CHECK,
    EXIT_ENVIRONMENT,
    EXIT_INPUT,
    EXIT_INTERRUPTED,
    EXIT_TERMINATED,
)


def _error_line(exc: BaseException) -> tuple[str, int]:
    """The one-line message and the exit code of an error that ends a command."""
    if isinstance(exc, OSError):
        from tumor3d.errors import os_error_line

        return os_error_line(exc), EXIT_ENVIRONMENT
    from tumor3d.flows.dask_runner import ClusterError
    from tumor3d.flows.server import ServerError
    from tumor3d.storage.refs import StoreError

    environment = StoreError | ServerError | ClusterError
    code = EXIT_ENVIRONMENT if isinstance(exc, environment) else EXIT_INPUT
    return str(exc) or type(exc).__name__, code


def _fail(exc: BaseException) -> typer.Exit:
    text, code = _error_line(exc)
    err_console.print(f"[bold red]error:[/] {escape(text)}", highlight=False, soft_wrap=True)
    return typer.Exit(code=code)


#: What the commands catch and turn into one line (anything else is a bug: traceback).
_HANDLED = (Tumor3DError, OSError)


def _crash_current_runs(message: str) -> None:
    """Set the flow runs this command is inside Crashed on their server (best effort).

    Called as an interrupted command ends: its runs would otherwise stay Running for
    good on a persistent server (the flow runs send no heartbeats, so nothing else
    notices). The innermost run of this thread and the flow runs above it; at most 2 s
    a request, no retries (a temporary server stopped by the same Ctrl-C refuses at
    once).
    """
    from prefect.context import FlowRunContext

    ctx = FlowRunContext.get()
    if ctx is None or ctx.flow_run is None:
        return
    from prefect.states import Crashed

    from tumor3d.flows.api_use import quick_client

    with quick_client() as client:
        run_id = ctx.flow_run.id
        for _ in range(4):  # a cohort inside an evaluation, ...
            client.set_flow_run_state(run_id, Crashed(message=message), force=True)
            parent = client.read_flow_run(run_id).parent_task_run_id
            if parent is None:
                return
            run_id = client.read_task_run(parent).flow_run_id


@contextmanager
def _ctrl_c_ends(message: str) -> Iterator[None]:
    """Ctrl-C (SIGINT) ends the command at once: one line on stderr, exit code 130.

    Unless the command was started with SIGINT ignored (a background job of a shell
    script), which it then keeps ignoring, in-process as through the warm runner.

    SIGTERM (what ``timeout``, systemd and Kubernetes send) alike, exit code 143,
    the line saying SIGTERM where ``message`` says Ctrl-C. The flow runs under way
    are set Crashed on their server, with that line (:func:`_crash_current_runs`).

    Python's KeyboardInterrupt did not stop a cohort: the main thread's
    interrupt waited for every patient lane to finish, and those lanes (with
    Prefect's event and log services) retried for minutes against the
    temporary Prefect server, which the same Ctrl-C had stopped (it shares
    the terminal's process group), printing their tracebacks. Here the
    process exits instead: nothing is published half (a patient is staged in
    a hidden folder and renamed at the end; a staging folder of this ended
    process is removed by the next publish of that patient), the temporary
    server dies with its parent (:mod:`tumor3d.flows.server`), and Prefect's unsent
    events are dropped. The exit hooks run first (:data:`tumor3d.flows.server_watch.EXIT_HOOKS`:
    a background runner's child reports the exit code to its client there). Install
    from the main thread only.
    """
    import contextlib
    import signal

    from tumor3d.flows.server_watch import EXIT_HOOKS, last_line

    def ends(code: int, line: str) -> Any:
        def on_signal(signum: int, frame: Any) -> None:
            # the line is the last thing on stderr: Prefect's services, whose temporary
            # server the same Ctrl-C stopped, would print their failures after it
            try:
                terminal = console.is_terminal
                if terminal:
                    with contextlib.suppress(Exception):
                        console.show_cursor(True)  # a live progress bar hides it
                with contextlib.suppress(Exception):
                    # on a terminal, stdout goes quiet too: the progress bar's redraws
                    # until the exit would erase the line
                    last_line(("\n" if terminal else "") + line, quiet_stdout=terminal)
                with contextlib.suppress(Exception):
                    _crash_current_runs(line)
            finally:
                for hook in EXIT_HOOKS:
                    with contextlib.suppress(Exception):
                        hook(code)
                os._exit(code)

        return on_signal

    terminated = message.replace("Ctrl-C", "SIGTERM", 1)
    previous = {
        signal.SIGTERM: signal.signal(
            signal.SIGTERM, ends(EXIT_TERMINATED, f"terminated: {terminated}")
        ),
    }
    # a SIGINT ignored by whoever started the command stays ignored (a shell script's
    # `tumor3d run ... &`: its job must outlive a Ctrl-C at the terminal), as the warm
    # runner's client, which relays only the SIGINT it receives, already let it (a user
    # audit: the same script's run stopped in-process and went on through the runner)
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
        previous[signal.SIGINT] = signal.signal(
            signal.SIGINT, ends(EXIT_INTERRUPTED, f"interrupted: {message}")
        )
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
