"""Prefect's own run records off the console: in the command's process and in Dask workers.

A command prints each failure as one line itself. Prefect also logs the
failed flow and task runs, with tracebacks, on its console handler; the
filter here drops those records from the console handlers only (they still
reach the Prefect server through its API handler, and ``--verbose`` keeps
them). A local Dask cluster's worker processes set up Prefect's logging
of their own, whose console is the command's stderr: the cohort's task
runner preloads this module in them (``dask_setup``) when the command's own
console is quiet (:func:`console_is_quiet`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import threading
from collections.abc import Iterator
from typing import Any

__all__ = [
    "NoOwnFailureTracebacks",
    "NoRunRecords",
    "console_is_quiet",
    "dask_setup",
    "own_failure_tracebacks_off",
    "quiet_run_records",
]


class NoRunRecords:
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
        """False for a record the console should not show."""
        name = record.name
        if name.startswith(("prefect.flow_runs", "prefect.task_runs")):
            return False
        return not str(record.msg).startswith("Still processing items")


def quiet_run_records() -> None:
    """Set up Prefect's logging (if not yet) and filter its console handlers."""
    from prefect.logging.configuration import ensure_logging_setup

    ensure_logging_setup()
    for handler in logging.getLogger().handlers:
        if not any(isinstance(f, NoRunRecords) for f in handler.filters):
            handler.addFilter(NoRunRecords())


class NoOwnFailureTracebacks:
    """Console filter of a Python call: drop Prefect's traceback of a bad input.

    A flow or task run that fails with an :class:`~tumor3d.errors.InputError` (an
    unreadable input, a bad configuration, a mask off the image's grid) is one line in
    the exception that ``run_patient`` or ``train`` raises (its cause chained), or in
    ``run_cohort``'s results; Prefect also logged it twice with its traceback (the task
    run, then the flow run), some 100 lines of a notebook's output before that line.
    Only those records are dropped, while a call runs
    (:func:`own_failure_tracebacks_off`): Prefect's one-line "Finished in state
    Failed(...)" stays, as do its other records and the traceback of any other
    exception; the Prefect server still gets them all (its API handler is not
    filtered).
    """

    def filter(self, record: Any) -> bool:
        """False for the record of a run that failed with a bad input."""
        from tumor3d.errors import InputError

        if not str(record.name).startswith(("prefect.flow_runs", "prefect.task_runs")):
            return True
        exc = record.exc_info[1] if record.exc_info else None
        return not isinstance(exc, InputError)


_OWN_FAILURES = NoOwnFailureTracebacks()
_OWN_FAILURES_LOCK = threading.Lock()
_own_failure_calls = 0


def _no_filter_in_a_forked_child() -> None:
    """A child forked during a call does not keep the call's filter for good."""
    global _own_failure_calls, _OWN_FAILURES_LOCK
    _own_failure_calls, _OWN_FAILURES_LOCK = 0, threading.Lock()
    for handler in logging.getLogger().handlers:
        handler.removeFilter(_OWN_FAILURES)


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_no_filter_in_a_forked_child)


@contextlib.contextmanager
def own_failure_tracebacks_off() -> Iterator[None]:
    """:class:`NoOwnFailureTracebacks` on Prefect's console handlers while the body runs.

    Counted: calls that overlap (threads) share the filter, the last to end removes it;
    the user's own flows outside a call keep their tracebacks (those in other threads
    while a call runs do not show a bad input's traceback either).
    """
    global _own_failure_calls
    from prefect.logging.configuration import ensure_logging_setup

    ensure_logging_setup()
    with _OWN_FAILURES_LOCK:
        _own_failure_calls += 1
        if _own_failure_calls == 1:
            for handler in logging.getLogger().handlers:
                handler.addFilter(_OWN_FAILURES)
    try:
        yield
    finally:
        with _OWN_FAILURES_LOCK:
            _own_failure_calls = max(0, _own_failure_calls - 1)  # (a forked child's: 0)
            if _own_failure_calls == 0:
                for handler in logging.getLogger().handlers:
                    handler.removeFilter(_OWN_FAILURES)


def console_is_quiet() -> bool:
    """Whether this process's console drops the run records (:func:`quiet_run_records`)."""
    return any(isinstance(f, NoRunRecords) for h in logging.getLogger().handlers for f in h.filters)


def dask_setup(worker: Any) -> None:
    """Dask's preload hook: a worker process's console as quiet as the command's."""
    quiet_run_records()
