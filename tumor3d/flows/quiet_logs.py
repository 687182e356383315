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

import logging
from typing import Any

__all__ = [
    "NoOwnFailureTracebacks",
    "NoRunRecords",
    "console_is_quiet",
    "dask_setup",
    "quiet_own_failure_tracebacks",
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
    """Console filter of a Python call: drop Prefect's traceback of tumor3d's own errors.

    A flow or task run that fails with a :class:`~tumor3d.errors.Tumor3DError` (an
    unreadable input, a bad configuration, a mask off the image's grid) is one line in
    the exception that ``run_patient``, ``run_cohort`` or ``train`` raises, or in the
    cohort's table; Prefect also logged it twice with its traceback (the task run, then
    the flow run), some 100 lines of a notebook's output before that line. Only those
    records are dropped: Prefect's one-line "Finished in state Failed(...)" stays, as do
    its other records and the traceback of any other exception (a defect's); the Prefect
    server still gets them all (its API handler is not filtered).
    """

    def filter(self, record: Any) -> bool:
        """False for the record of a run that failed with one of tumor3d's own errors."""
        from tumor3d.errors import Tumor3DError

        if not str(record.name).startswith(("prefect.flow_runs", "prefect.task_runs")):
            return True
        exc = record.exc_info[1] if record.exc_info else None
        return not isinstance(exc, Tumor3DError)


def quiet_own_failure_tracebacks() -> None:
    """Set up Prefect's logging (if not yet) and filter its console handlers (a Python call)."""
    from prefect.logging.configuration import ensure_logging_setup

    ensure_logging_setup()
    for handler in logging.getLogger().handlers:
        if not any(isinstance(f, NoOwnFailureTracebacks) for f in handler.filters):
            handler.addFilter(NoOwnFailureTracebacks())


def console_is_quiet() -> bool:
    """Whether this process's console drops the run records (:func:`quiet_run_records`)."""
    return any(isinstance(f, NoRunRecords) for h in logging.getLogger().handlers for f in h.filters)


def dask_setup(worker: Any) -> None:
    """Dask's preload hook: a worker process's console as quiet as the command's."""
    quiet_run_records()
