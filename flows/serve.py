"""Scheduled reprocessing: a Prefect deployment of the cohort flow on a cron schedule.

Wiring only. :func:`scheduled_cohort_flow` is the deployed flow: each run
re-reads the manifest (and the configuration file, if any) and runs
:func:`tumor3d.flows.cohort.run_cohort` as a subflow, so new or changed inputs
compute, unchanged ones are stage cache hits (cache keys hold the input's
content digest, never the run), and patients published earlier but no longer
in the manifest are reported in ``cohort.md`` and the result, not deleted.

:func:`cohort_deployment` builds the deployment object
(``flow.to_deployment``) without starting anything, so a test can inspect its
schedule and parameters; :func:`serve_cohort` hands it to Prefect's
``serve`` (blocks, polling the Prefect API for scheduled and UI-triggered
runs).

Every run ends in a Prefect state that says how it went, so the Prefect UI,
automations and notifications see a failure: **Failed** when some patient
failed (the cohort outputs are still written; the message names up to three of
them) or when a project error (:class:`tumor3d.errors.Tumor3DError`: a manifest
or configuration broken after ``serve`` started, an unreachable store) or an
environment error (``OSError``: an output folder that cannot be written)
stopped the run; the error is then one line on the run's logger, no traceback, and the
state's message. A patient with status ``check`` is not a failure: the run is
Completed, its message says how many need a check. Any other exception is a bug
and propagates as Prefect reports it. Each run also records its outcome in
``DIR/last_run.json`` (:data:`LAST_RUN_FILE`), so a folder whose ``cohort.md``
is an earlier run's does not look current after a run that failed before
writing it.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from prefect import flow, get_run_logger
from prefect.deployments.runner import EntrypointType, RunnerDeployment
from prefect.states import Completed, Failed, State

from tumor3d.errors import InputError, Tumor3DError
from tumor3d.flows.cohort import run_cohort
from tumor3d.flows.cohort_result import CohortResult, one_line_error
from tumor3d.flows.dask_runner import DaskSpec
from tumor3d.segmentation.review import STATUS_CHECK, STATUS_FAILED, STATUS_OK
from tumor3d.storage.given_models import read_config_file
from tumor3d.storage.objectstore import is_url
from tumor3d.storage.store import atomic_write_bytes, utc_now

__all__ = [
    "DEFAULT_DEPLOYMENT_NAME",
    "LAST_RUN_FILE",
    "cohort_deployment",
    "load_config_file",
    "run_message",
    "scheduled_cohort_flow",
    "serve_cohort",
]

#: Deployment name when ``--name`` is not given.
DEFAULT_DEPLOYMENT_NAME = "tumor3d-cohort-nightly"

#: The outcome of the latest scheduled run, in ``DIR`` (written by every run, at its end).
LAST_RUN_FILE = "last_run.json"

#: Failed patients named in a run's message (the others are counted).
_NAMED_FAILURES = 3
#: Longest error of a patient quoted in a run's message (characters).
_MESSAGE_ERROR = 100


def load_config_file(path: str | Path | None) -> dict[str, Any]:
    """The validated configuration of a YAML file as a JSON-able dict ({} for None).

    Raises
    ------
    ConfigError
        An unreadable file or an invalid configuration (naming the file).
    InputError
        Its ``segment.learned_models`` folder is not one
        (:func:`tumor3d.storage.given_models.read_config_file`).
    """
    return {} if path is None else read_config_file(path).model_dump(mode="json")


#: The fields of a cron expression and their ranges.
_CRON_FIELDS = (("minute", 0, 59), ("hour", 0, 23), ("day of month", 1, 31),
                ("month", 1, 12), ("day of week", 0, 7))  # fmt: skip


def _cron_reason(cron: str, exc: ValueError) -> str:
    """Why a cron expression was refused, in words (no validation-library URL)."""
    fields = cron.split()
    if len(fields) != len(_CRON_FIELDS):
        return (
            f"a cron expression has 5 fields (minute hour day-of-month month day-of-week), "
            f"this one {len(fields)}"
        )
    for text, (name, low, high) in zip(fields, _CRON_FIELDS, strict=True):
        for number in re.findall(r"\d+", text):
            if not low <= int(number) <= high:
                return f"{name} {number} is outside {low}-{high}"
    errors = getattr(exc, "errors", None)
    msg = errors()[0]["msg"] if callable(errors) and errors() else str(exc).splitlines()[0]
    return str(msg).removeprefix("Value error, ")


@flow(name="tumor3d-scheduled-cohort", persist_result=False, log_prints=False)
def scheduled_cohort_flow(
    manifest: str,
    out_dir: str,
    config_path: str | None = None,
    workers: int | None = None,
    store_dir: str | None = None,
    dask_address: str | None = None,
    dask_workers: int | None = None,
) -> State[CohortResult]:
    """Re-read ``manifest`` and run the cohort flow on it (one scheduled run).

    The run's final state says how it went (module docstring): Completed with
    the :class:`~tumor3d.flows.cohort.CohortResult` as its result (what a
    direct call returns) when no patient failed; Failed, with a one-line
    message, when some patient failed or a project error stopped the run.
    Either way the outcome is written to ``DIR/last_run.json``.

    Parameters
    ----------
    manifest : str
        Cohort manifest CSV, read afresh by every run.
    out_dir : str
        Output folder (``DIR``), the same for every run.
    config_path : str, optional
        YAML configuration file, read afresh by every run.
    workers : int, optional
        Patients at a time; default the CPU cores (or the Dask workers).
    store_dir : str, optional
        Artifact store; default ``DIR/.tumor3d-store``.
    dask_address, dask_workers : optional
        Run the stages on Dask (:mod:`tumor3d.flows.dask_runner`).
    """
    logger = get_run_logger()
    started = utc_now()
    _tag_with_this_process()
    try:
        result = run_cohort(
            manifest, out_dir, config=load_config_file(config_path), workers=workers,
            store_dir=store_dir, dask=DaskSpec(dask_address, dask_workers),
        )  # fmt: skip
    except (Tumor3DError, OSError) as exc:  # the user's to fix, as the CLI's: one line, Failed
        line = one_line_error(exc)
        logger.error("scheduled run failed: %s", line)
        _write_last_run(out_dir, started, "failed", line, None, logger)
        return _failed(line)
    except Exception as exc:  # a bug: recorded, then Prefect reports it as it does
        _write_last_run(out_dir, started, "failed", one_line_error(exc), None, logger)
        raise
    message = run_message(result)
    if result.failed:
        logger.error("scheduled run failed: %s", message)
        _write_last_run(out_dir, started, "failed", message, result, logger)
        return _failed(message)
    (logger.warning if result.to_check else logger.info)("scheduled run: %s", message)
    _write_last_run(out_dir, started, "completed", message, result, logger)
    return Completed(message=message, data=result)


def _tag_with_this_process() -> None:
    """Tag the running scheduled run with the process Prefect runs it in.

    Its process tags (:func:`tumor3d.flows.stale_runs.process_tags`) let the next
    command's sweep set it Crashed if that process ends without reporting: ``serve``
    stopped by SIGTERM or Ctrl-C mid-run left it Running for good, holding the
    deployment's one slot (concurrency limit 1), so a restarted ``serve`` ran nothing
    for minutes and said nothing (a user audit). Best effort: a run is never stopped
    by it.
    """
    import contextlib

    from prefect.context import FlowRunContext

    from tumor3d.flows.api_use import quick_client
    from tumor3d.flows.stale_runs import process_tags

    ctx = FlowRunContext.get()
    extra = process_tags()
    if ctx is None or ctx.flow_run is None or not extra:
        return
    with contextlib.suppress(Exception), quick_client() as client:
        tags = sorted(set(ctx.flow_run.tags) | set(extra))
        client.update_flow_run(ctx.flow_run.id, tags=tags)


class _NoShutdownTraceback(logging.Filter):
    """Drops asyncio's records of callbacks cancelled as ``serve`` shuts down.

    SIGTERM ends Prefect's runner by ``sys.exit(0)`` inside its event loop; the
    callbacks of its control channel then fail with ``CancelledError`` and asyncio logs
    each with its traceback ("Exception in callback ...", a user audit saw it on
    stderr). Only records whose exception is a cancellation or that exit are dropped.

    >>> import asyncio
    >>> def record(exc):
    ...     return logging.LogRecord("asyncio", logging.ERROR, "", 0, "cb", None,
    ...                              (type(exc), exc, None))
    >>> f = _NoShutdownTraceback()
    >>> f.filter(record(asyncio.CancelledError())), f.filter(record(ValueError("bug")))
    (False, True)
    """

    def filter(self, record: logging.LogRecord) -> bool:
        import asyncio

        exc = record.exc_info[1] if record.exc_info else None
        return not isinstance(exc, asyncio.CancelledError | SystemExit)


class _NoTracebackOfOwnFailures(logging.Filter):
    """Drops Prefect's traceback of a run that :func:`scheduled_cohort_flow` ended Failed.

    When a flow returns a Failed state, a runner's process (``python -m
    prefect.engine``, how ``serve`` executes a run) asks the engine for the run's
    result, which raises the state as ``FailedRun``, and logs that with its
    traceback as "Engine execution exited with unexpected exception"
    (``prefect.flow_engine.run_flow``, Prefect 3.8). The failure is already one
    line on the run's logger and the state's message; only the ``FailedRun``
    records of the runs listed here are dropped (any other exception keeps its
    traceback).
    """

    def __init__(self) -> None:
        super().__init__()
        self.run_ids: set[str] = set()

    def filter(self, record: logging.LogRecord) -> bool:
        from prefect.exceptions import FailedRun

        exc = record.exc_info[1] if record.exc_info else None
        return not (
            isinstance(exc, FailedRun) and getattr(record, "flow_run_id", None) in self.run_ids
        )


_NO_TRACEBACK = _NoTracebackOfOwnFailures()


def _failed(message: str) -> State[Any]:
    """The Failed state of this run, whose ``FailedRun`` Prefect then logs without a traceback."""
    from prefect.runtime import flow_run

    _NO_TRACEBACK.run_ids.add(str(flow_run.id))
    logging.getLogger("prefect.flow_runs").addFilter(_NO_TRACEBACK)  # once: same instance
    return Failed(message=message)


def run_message(result: CohortResult) -> str:
    """One line on a cohort run: who failed (three named, with stage and error), who needs a check.

    Examples
    --------
    >>> from tumor3d.flows.cohort import PatientOutcome
    >>> ok = PatientOutcome(patient_id="p0", status="ok")
    >>> bad = PatientOutcome(patient_id="p1", status="failed", failed_stage="segment",
    ...                      error="ValueError: empty")
    >>> run_message(CohortResult(patients=[ok, bad]))
    '1 of 2 patients failed: p1 (segment: ValueError: empty)'
    >>> run_message(CohortResult(patients=[ok, PatientOutcome(patient_id="p2", status="check")]))
    '2 patients completed, 1 needs a check: p2'
    """
    n = len(result.patients)
    failed, check = result.failed, result.to_check
    needs = f"{len(check)} {'needs' if len(check) == 1 else 'need'} a check"
    if failed:
        named = _some(f"{p.patient_id} ({p.failed_stage}: {_cut(p.error or '?')})" for p in failed)
        return f"{len(failed)} of {n} patients failed: {named}" + (f"; {needs}" if check else "")
    text = f"{n} patient{'' if n == 1 else 's'} completed"
    return text + (f", {needs}: {_some(p.patient_id for p in check)}" if check else "")


def _some(items: Iterable[str]) -> str:
    """The first :data:`_NAMED_FAILURES` of ``items``, then how many more."""
    listed = list(items)
    more = len(listed) - _NAMED_FAILURES
    return ", ".join(listed[:_NAMED_FAILURES]) + (f" and {more} more" if more > 0 else "")


def _cut(text: str, limit: int = _MESSAGE_ERROR) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."


def _write_last_run(
    out_dir: str,
    started: str,
    state: str,
    message: str,
    result: CohortResult | None,
    logger: Any,
) -> None:
    """Write ``DIR/last_run.json`` atomically (a local ``DIR`` only; ``serve`` takes no URL).

    A failure to write it is a warning: the run's state already says how it went.
    """
    if is_url(out_dir):
        return
    from prefect.runtime import flow_run

    statuses = [p.status for p in result.patients] if result is not None else []
    record = {
        "flow_run_id": flow_run.id,
        "started_utc": started,
        "finished_utc": utc_now(),
        "state": state,
        "message": message,
        "patients": {s: statuses.count(s) for s in (STATUS_OK, STATUS_CHECK, STATUS_FAILED)},
    }
    changed = {} if result is None else result.since_earlier  # published before: why
    if changed:
        record["since_earlier_result"] = changed
    path = Path(out_dir) / LAST_RUN_FILE
    try:
        atomic_write_bytes(path, (json.dumps(record, indent=1) + "\n").encode())
    except OSError as exc:
        logger.warning("cannot write %s: %s", path, one_line_error(exc))


def cohort_deployment(
    manifest: str | Path,
    out_dir: str | Path,
    *,
    cron: str,
    name: str = DEFAULT_DEPLOYMENT_NAME,
    config_path: str | Path | None = None,
    workers: int | None = None,
    store_dir: str | Path | None = None,
    dask_address: str | None = None,
    dask_workers: int | None = None,
    timezone: str = "UTC",
) -> RunnerDeployment:
    """The deployment of :func:`scheduled_cohort_flow` with a cron schedule (not started).

    Paths are made absolute, since a scheduled run may start in another
    working folder. The manifest and configuration are checked once here, so
    a typo fails at ``serve`` time rather than at 2 a.m. A row whose image is
    not there yet is accepted, as ``cohort`` accepts it: each run fails that
    row alone (a scan that arrives later is run by the next schedule).

    Raises
    ------
    InputError
        An invalid cron expression or time zone, a missing or invalid
        manifest or an invalid configuration.
    """
    import zoneinfo

    from prefect.client.schemas.schedules import CronSchedule

    from tumor3d.storage.manifest import read_manifest

    try:
        zoneinfo.ZoneInfo(timezone)
    except (zoneinfo.ZoneInfoNotFoundError, ValueError):
        raise InputError(
            f"invalid --timezone {timezone!r}: not an IANA time zone (UTC, Europe/Paris, ...)"
        ) from None
    try:
        schedule = CronSchedule(cron=cron, timezone=timezone)
    except ValueError as exc:
        raise InputError(f"invalid --cron {cron!r}: {_cron_reason(cron, exc)}") from None
    manifest_path = Path(manifest).expanduser().resolve()
    read_manifest(manifest_path, require_files=False)
    cfg_path = None if config_path is None else Path(config_path).expanduser().resolve()
    load_config_file(cfg_path)
    DaskSpec(dask_address, dask_workers)
    parameters: dict[str, Any] = {
        "manifest": str(manifest_path),
        "out_dir": str(Path(out_dir).expanduser().resolve()),
        "config_path": None if cfg_path is None else str(cfg_path),
        "workers": workers,
        "store_dir": None if store_dir is None else _location(store_dir),
        "dask_address": dask_address,
        "dask_workers": dask_workers,
    }
    return scheduled_cohort_flow.to_deployment(
        name=name,
        schedule=schedule,
        # one run at a time: a run triggered while another writes DIR waits for it
        concurrency_limit=1,
        parameters=parameters,
        tags=["tumor3d", "cohort", "scheduled"],
        description=f"tumor3d cohort of {manifest_path} into {parameters['out_dir']}, "
        f"cron {cron!r} ({timezone})",
        entrypoint_type=EntrypointType.MODULE_PATH,
    )


def _location(value: str | Path) -> str:
    """A store location: URLs as given, paths made absolute."""
    text = str(value)
    return text if "://" in text else str(Path(text).expanduser().resolve())


def serve_cohort(deployment: RunnerDeployment) -> None:  # pragma: no cover - blocks
    """Serve the deployment with Prefect (blocks until interrupted).

    SIGTERM (systemd, ``kill``) ends it through Prefect's own handler
    (``Runner.handle_sigterm``: exit 0), which creates ``Runner.astop`` without awaiting
    it; the RuntimeWarning that leaves on stderr at exit is Prefect's and is not shown.
    The scheduled runs are not given this process's tags (:mod:`tumor3d.flows.stale_runs`):
    Prefect runs each in a process of its own, which tags its run as it starts
    (:func:`_tag_with_this_process`), as the cohort run inside it is tagged
    (``run_cohort``'s Python call); a run whose process ended is set Crashed by the next
    command, a restarted ``serve`` included, which frees the deployment's slot.
    """
    import warnings

    from prefect import serve
    from prefect.context import TagsContext

    warnings.filterwarnings(
        "ignore", message="coroutine 'Runner.astop' was never awaited", category=RuntimeWarning
    )
    quiet = _NoShutdownTraceback()
    logging.getLogger("asyncio").addFilter(quiet)
    try:
        with TagsContext(current_tags=set()):
            serve(deployment)
    finally:
        logging.getLogger("asyncio").removeFilter(quiet)
