"""The Prefect session a command runs in: quiet logs, no heartbeats, a reporter per stage."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from tumor3d.flows.cli.app import console
from tumor3d.flows.cli.output import _PlainReporter, _progress, _ProgressReporter
from tumor3d.flows.quiet_logs import quiet_run_records


def _starting_prefect_note() -> None:
    console.print(
        "[dim]starting Prefect: a temporary local server for this command (10-20 s; "
        "`tumor3d server start` keeps one running for fast repeated runs)...[/]"
    )


def _quiet_prefect_failures() -> None:
    if "--verbose" in sys.argv or "-v" in sys.argv:
        return
    quiet_run_records()


@contextmanager
def _no_heartbeats() -> Iterator[None]:
    """Flow-run heartbeats off for a command, unless PREFECT_FLOWS_HEARTBEAT_FREQUENCY is set.

    Prefect's heartbeat thread sleeps in 1 s steps and the flow engine joins
    it when the run ends: about 0.9 s of every command, for a signal that
    only a server automation (not set up by default) would use.
    """
    if os.environ.get("PREFECT_FLOWS_HEARTBEAT_FREQUENCY"):
        yield
        return
    from prefect.settings import temporary_settings

    with temporary_settings(updates={"flows.heartbeat_frequency": None}):
        yield


@contextmanager
def _prefect() -> Iterator[str]:
    """PREFECT_API_URL, else the background server, else a temporary one (flows.api_use)."""
    from tumor3d.flows.api_use import prefect_api

    with prefect_api(on_temporary_start=_starting_prefect_note) as api_url, _no_heartbeats():
        _quiet_prefect_failures()
        yield api_url


@contextmanager
def _reporting(make_reporter: Any) -> Iterator[None]:
    """A live progress bar on a terminal, plain lines otherwise."""
    from tumor3d.flows.progress import use_reporter

    if not console.is_terminal:
        with use_reporter(_PlainReporter()):
            yield
        return
    with _progress() as progress, use_reporter(make_reporter(progress)):
        yield


def _run_with_progress(**kwargs: Any) -> Any:
    """``run_patient`` with the console's progress, under Prefect.

    Ctrl-C ends it at once, one line and exit 130, as ``cohort``
    (:func:`tumor3d.flows.cli.errors._ctrl_c_ends`).
    """
    from tumor3d.flows.cli.errors import _ctrl_c_ends
    from tumor3d.flows.patient import run_patient

    stopped = "Ctrl-C stopped the run; a re-run continues from the cache"
    with _ctrl_c_ends(stopped), _prefect(), _reporting(_ProgressReporter):
        return run_patient(**kwargs)
