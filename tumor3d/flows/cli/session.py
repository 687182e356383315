"""The Prefect session a command runs in: quiet logs, no heartbeats, a reporter per stage."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from tumor3d.flows.cli.app import console
from tumor3d.flows.cli.output import _PlainReporter, _progress, _ProgressReporter


def _starting_prefect_note() -> None:
    console.print(
        "[dim]starting Prefect: a temporary local server for this command (10-20 s; "
        "`tumor3d server start` keeps one running for fast repeated runs)...[/]"
    )


class _NoFailureTracebacks:
    """Console filter: drop Prefect's own records of flow and task runs (any level).

    Their warnings and errors repeat, under a run name and with a traceback,
    what the command prints itself as one line (a failed patient, a skipped
    row, a patient no longer in the manifest); they still reach the Prefect
    server (its API handler is not filtered), and ``--verbose`` shows them.
    So does a background service's "Still processing items" while it sends
    its last events as the command ends (Prefect's ``EventsWorker``): not the
    user's to act on.
    """

    def filter(self, record: Any) -> bool:
        name = record.name
        if name.startswith(("prefect.flow_runs", "prefect.task_runs")):
            return False
        return not str(record.msg).startswith("Still processing items")


def _quiet_prefect_failures() -> None:
    import logging

    from prefect.logging.configuration import ensure_logging_setup

    if "--verbose" in sys.argv or "-v" in sys.argv:
        return
    ensure_logging_setup()
    for handler in logging.getLogger().handlers:
        if not any(isinstance(f, _NoFailureTracebacks) for f in handler.filters):
            handler.addFilter(_NoFailureTracebacks())


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
    """PREFECT_API_URL, else the background server, else a temporary one (flows.server)."""
    from tumor3d.flows.server import prefect_api

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
