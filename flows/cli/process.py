"""Running a command to its end in this process (``main``) or in the warm runner."""

from __future__ import annotations

import os
import sys

from tumor3d.flows.cli.app import app


def finish_process() -> None:
    """Run every exit handler and flush the standard streams.

    The handlers: Prefect sends its buffered logs and events, ``logging``
    flushes its handlers.
    """
    import atexit

    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass


def run_command(args: list[str] | None = None, prog_name: str | None = None) -> int:
    """Run a command to its end (:func:`finish_process`); its exit code.

    ``sys.exit("message")`` prints the message and gives 1. Used by
    :func:`main` and by the warm runner's copy of itself (:mod:`tumor3d.flows.daemon`).
    """
    code: int | str | None = 0
    try:
        app(args=args, prog_name=prog_name)
    except SystemExit as exc:
        code = exc.code
    finish_process()
    if isinstance(code, str):  # sys.exit("message") prints it and exits 1
        print(code, file=sys.stderr, flush=True)
        code = 1
    return int(code or 0)


def main() -> None:  # pragma: no cover - console entry
    """Entry point (``tumor3d``, ``python -m tumor3d.flows.cli``): run the command, then exit fast.

    Once the command has finished and :func:`finish_process` has run, the
    process ends with :func:`os._exit`: tearing down the interpreter with
    Prefect, scipy, numba and VTK loaded takes another 1.2-1.6 s and does
    nothing useful. Every output is written and closed before this point.
    """
    os._exit(run_command())
