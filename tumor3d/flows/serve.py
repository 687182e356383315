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
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

from prefect import flow
from prefect.deployments.runner import EntrypointType, RunnerDeployment

from tumor3d.config import parse_config
from tumor3d.errors import ConfigError, InputError
from tumor3d.flows.cohort import CohortResult, run_cohort
from tumor3d.flows.dask_runner import DaskSpec

__all__ = [
    "DEFAULT_DEPLOYMENT_NAME",
    "cohort_deployment",
    "load_config_file",
    "scheduled_cohort_flow",
    "serve_cohort",
]

#: Deployment name when ``--name`` is not given.
DEFAULT_DEPLOYMENT_NAME = "tumor3d-cohort-nightly"


def load_config_file(path: str | Path | None) -> dict[str, Any]:
    """The validated configuration of a YAML file as a JSON-able dict ({} for None).

    Raises
    ------
    ConfigError
        An unreadable file or an invalid configuration (naming the file).
    """
    if path is None:
        return {}
    try:
        text = Path(path).read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read configuration: {exc.strerror}", path=str(path)) from None
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start})",
            path=str(path),
        ) from None
    return parse_config(text, source=str(path)).model_dump(mode="json")


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
) -> CohortResult:
    """Re-read ``manifest`` and run the cohort flow on it (one scheduled run).

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
    return run_cohort(
        manifest, out_dir, config=load_config_file(config_path), workers=workers,
        store_dir=store_dir, dask=DaskSpec(dask_address, dask_workers),
    )  # fmt: skip


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
    """Serve the deployment with Prefect (blocks until interrupted)."""
    from prefect import serve

    serve(deployment)
