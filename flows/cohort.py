"""Cohort flow: the single-patient pipeline for every manifest row, N patients at a time.

Wiring only. :func:`cohort_flow` runs :func:`tumor3d.flows.patient.patient_pipeline`
for each row in a pool of ``workers + 1`` lanes (:data:`EXTRA_LANES`); each lane
submits its stages to the flow's task runner (threads, ``workers`` wide), so
``workers`` stages compute at once while one more patient's lane publishes (in
the flow's own process) or waits for a worker; a different task runner (Dask)
can be given to the flow with ``cohort_flow.with_options(task_runner=...)``
without touching the stages:
:func:`run_cohort` does so for ``dask=DaskSpec(...)``
(:mod:`tumor3d.flows.dask_runner`). The store may be a folder or an object-store URL
(:mod:`tumor3d.storage.objectstore`); either is checked before any patient starts.
So may ``DIR``: with ``s3://bucket/prefix`` each patient is staged locally and
published to ``<url>/<patient_id>/`` with a completion marker written last
(:mod:`tumor3d.storage.remote_publish`); the store then defaults to
``<url>/.tumor3d-store``.

Patients published in ``DIR`` by an earlier run but no longer in the rows are
reported (``CohortResult.removed``, ``cohort.md``), never deleted.

Failure isolation: a patient that fails (unreadable image, no brain found,
any exception) is recorded with its status, the failing stage and a one-line
error; the others finish and are published. Nothing is half-written under any
patient's final folder (:mod:`tumor3d.storage.publish`). ``DIR/cohort.parquet`` and
``DIR/cohort.md`` summarise the cohort (:mod:`tumor3d.storage.cohort_report`).

What the flow returns, and how a failure is told apart (the machine's or the
input's), is :mod:`tumor3d.flows.cohort_result` (:class:`CohortResult`,
:class:`PatientOutcome`, :class:`PatientsFailed`, :func:`exit_code_of`,
:func:`one_line_error`: re-exported here); the checks of the rows before any work are
:func:`tumor3d.storage.cohort_rows.validate_rows`.
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import functools
import os
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

from prefect import flow, get_run_logger, tags
from prefect.states import Failed, State

from tumor3d.config import PipelineConfig, as_config, parse_config
from tumor3d.constants import MAX_VOXELS_DEFAULT
from tumor3d.errors import InputError
from tumor3d.flows.api_use import api_of_python_call
from tumor3d.flows.artifacts import publish_cohort_artifacts
from tumor3d.flows.cohort_result import (
    CohortResult,
    PatientOutcome,
    PatientsFailed,
    environment_failure,
    exit_code_of,
    one_line_error,
    with_recompute_reason,
)
from tumor3d.flows.dask_runner import DaskSpec, check_scheduler, cohort_task_runner
from tumor3d.flows.dask_workers import check_workers
from tumor3d.flows.exit_codes import EXIT_CHECK
from tumor3d.flows.patient import (
    VOLUME_LABELS,
    config_digest,
    patient_pipeline,
    prepare_brain_mask,
    prepare_models,
    prepare_segmentation,
    prepare_source,
    sweep_killed_writers,
)
from tumor3d.segmentation.review import STATUS_FAILED, STATUS_OK
from tumor3d.storage import bids
from tumor3d.storage.cohort_report import (
    cohort_markdown,
    cohort_output_files,
    cohort_table,
    cohort_title,
    published_patient_ids,
    write_cohort_outputs,
)
from tumor3d.storage.cohort_rows import validate_rows
from tumor3d.storage.folder_lock import writing_folder
from tumor3d.storage.manifest import ManifestRow, read_manifest
from tumor3d.storage.objectstore import ObjectStore, default_store_location, is_url, open_store
from tumor3d.storage.provenance import cache_identity
from tumor3d.storage.remote_publish import RemoteFolder, publish_files, published_names
from tumor3d.storage.store import ArtifactStore, check_writable_dir
from tumor3d.tasks import stages
from tumor3d.tasks.progress import ProgressEvent, report
from tumor3d.tasks.runner import StageRun

__all__ = [  # with the result types re-exported (tumor3d.flows.cohort_result)
    "CohortResult",
    "EXIT_CHECK",
    "EXTRA_LANES",
    "PatientOutcome",
    "PatientsFailed",
    "cohort_flow",
    "default_workers",
    "exit_code_of",
    "one_line_error",
    "run_cohort",
]

#: Patients in flight beyond the task runner's width. A lane publishes its patient in
#: the flow's own process after the last stage (0.4 s a phantom patient, ~15 % of its
#: lane); with one lane per worker that worker idled meanwhile. One more lane keeps
#: the workers busy: its stages wait in the task runner's queue (issue 32 item 3).
EXTRA_LANES = 1


def default_workers() -> int:
    """Patients at a time by default: the number of CPU cores."""
    return max(1, os.cpu_count() or 1)


def _row_dict(row: ManifestRow | dict[str, Any]) -> dict[str, Any]:
    data = dataclasses.asdict(row) if dataclasses.is_dataclass(row) else dict(row)
    return {k: (str(v) if isinstance(v, Path) else v) for k, v in data.items()}


def _json_row(row: dict[str, Any]) -> dict[str, Any]:
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in row.items()}


def _run_one(
    row: dict[str, Any],
    out_dir: str,
    cfg: PipelineConfig,
    store: ArtifactStore,
    max_voxels: int = MAX_VOXELS_DEFAULT,
    layout: str = "default",
) -> PatientOutcome:
    """One lane: prepare, run every stage, publish; any failure becomes an outcome."""
    t0 = time.perf_counter()
    pid = str(row.get("patient_id"))
    names = list(stages.STAGES)
    runs: list[StageRun] = []
    prepared = False
    try:
        source = prepare_source(
            row["image"], patient_id=pid, modality=row.get("modality") or "t2",
            series_uid=row.get("series_uid"), slice_thickness_mm=row.get("slice_thickness_mm"),
            slice_gap_mm=row.get("slice_gap_mm"), max_voxels=max_voxels, out_dir=out_dir,
        )  # fmt: skip
        mask = row.get("brain_mask")
        given = None if not mask else prepare_brain_mask(mask, source, out_dir=out_dir)
        seg_path = row.get("segmentation")
        seg = None if not seg_path else prepare_segmentation(seg_path, source, out_dir=out_dir)
        prepare_models(cfg, source, seg)  # the folder holds this sequence's model, if used
        prepared = True
        result = patient_pipeline(
            source, out_dir, cfg, store, runs=runs, brain_mask=given, segmentation=seg,
            layout=layout,
        )  # fmt: skip
    except Exception as exc:  # failure isolation: record and let the others finish
        done = len(runs)
        if not prepared:
            stage = "prepare-input"
        else:
            stage = names[done] if done < len(names) else "publish"
        report(ProgressEvent(pid, stage, "failed", done, len(names)))
        return PatientOutcome(
            patient_id=pid, status=STATUS_FAILED, failed_stage=stage, error=one_line_error(exc),
            environment=environment_failure(exc, input_read=prepared),
            stages=list(runs), row=_json_row(row), lane_seconds=time.perf_counter() - t0,
        )  # fmt: skip
    # "up to date": every stage cached and the published folder already this result
    said = "up to date" if result.up_to_date else "published"
    report(ProgressEvent(pid, said, "published", len(names), len(names)))
    return PatientOutcome(
        patient_id=pid, status=str(result.metrics.get("status", STATUS_OK)),
        output_dir=result.output_dir, metrics=result.metrics,
        stages=result.stages, row=_json_row(row), lane_seconds=time.perf_counter() - t0,
        publish_seconds=result.publish_seconds,
    )  # fmt: skip


def _cohort_run_name() -> str:
    from prefect.runtime import flow_run

    params = flow_run.parameters
    name = Path(str(params.get("out_dir", "cohort"))).name
    return f"cohort-{name}-{len(params.get('rows') or [])}-patients"


@flow(name="tumor3d-cohort", flow_run_name=_cohort_run_name, persist_result=False)
def cohort_flow(
    rows: list[dict[str, Any]],
    out_dir: str,
    config: dict[str, Any] | None = None,
    workers: int = 1,
    store_dir: str | None = None,
    max_voxels: int = MAX_VOXELS_DEFAULT,
    layout: str = "default",
) -> CohortResult | State[CohortResult]:
    """Run the single-patient pipeline for every row, ``workers`` stages at a time.

    Parameters
    ----------
    rows : list of dict
        Manifest rows (``patient_id``, ``image``, ``modality``, optional
        ``slice_thickness_mm``, ``slice_gap_mm``, ``series_uid``,
        ``brain_mask``, ``segmentation``; other keys are passed through to the
        outcome). A row whose image, brain mask or segmentation is missing or
        bad fails alone, at ``prepare-input``.
    out_dir : str
        ``DIR``: patients under ``DIR/<patient_id>/``, plus ``cohort.parquet``
        and ``cohort.md``.
    config : dict, optional
        Pipeline configuration for every patient.
    workers : int
        Stages at a time (>= 1): the task runner's width; ``workers +``
        :data:`EXTRA_LANES` patients are in flight.
    store_dir : str, optional
        Artifact store shared by all patients; default ``DIR/.tumor3d-store``.
    max_voxels : int
        Refuse an input whose header declares more voxels (that row fails).
    layout : {"default", "bids"}
        ``"bids"``: patients under ``DIR/sub-<label>/`` as BIDS derivatives
        (:mod:`tumor3d.storage.bids`).

    Returns
    -------
    CohortResult or State
        The result; when some patient failed, a ``Failed`` state holding
        :class:`PatientsFailed` (the flow run is then Failed in Prefect, as a
        scheduled run is). A direct call then raises that error, whose ``result``
        is the whole result; :func:`run_cohort` returns the result either way.
    """
    t0 = time.perf_counter()
    cfg = parse_config(config or {}, source="config")
    store = open_store(store_dir or _default_store(out_dir))
    logger = get_run_logger()
    logger.info("cohort of %d patients, %d workers, config %s", len(rows), workers,
                config_digest(cfg)[:12])  # fmt: skip
    listed = {bids.folder_name(str(r.get("patient_id")), layout) for r in rows}
    remote = RemoteFolder(out_dir) if is_url(out_dir) else None
    published = published_patient_ids(out_dir) if remote is None else published_names(remote)
    removed = [pid for pid in published if pid not in listed]
    if removed:
        logger.warning("%d published patient(s) no longer in the manifest, kept: %s",
                       len(removed), ", ".join(removed))  # fmt: skip
    # what decided each published patient's cache keys, to say why its result changed
    before = {} if remote is not None else {
        f: cache_identity(Path(out_dir) / f) for f in listed if f in published
    }  # fmt: skip
    for spec in stages.STAGES.values():  # per-process constants, once, before the lanes start
        _ = spec.code_digest
    lanes = max(1, min(len(rows), workers + EXTRA_LANES))
    with ThreadPoolExecutor(max_workers=lanes, thread_name_prefix="tumor3d-lane") as pool:
        lane = functools.partial(
            _run_one, out_dir=out_dir, cfg=cfg, store=store, max_voxels=max_voxels, layout=layout
        )
        futures = [pool.submit(contextvars.copy_context().run, lane, row) for row in rows]
        outcomes = [f.result() for f in futures]
    sweep_killed_writers(store, logger)  # of writers killed mid-stage (a lost Dask worker)
    if before:
        outcomes = [with_recompute_reason(o, before, layout) for o in outcomes]
        for o in outcomes:
            if o.recomputed:  # a warning: the flow run's log on the server (not the console)
                logger.warning("patient %s changed since its earlier result: %s",
                               o.patient_id, o.recomputed)  # fmt: skip
    wall = time.perf_counter() - t0
    table = cohort_table([o.model_dump() for o in outcomes], out_dir=out_dir)
    earlier = [
        o.patient_id for o in outcomes
        if o.status == STATUS_FAILED and bids.folder_name(o.patient_id, layout) in published
    ]  # fmt: skip
    markdown = cohort_markdown(
        table, volume_labels=VOLUME_LABELS, stage_names=list(stages.STAGES),
        title=cohort_title(Path(out_dir).name), wall_seconds=wall, workers=workers,
        removed=removed, earlier=earlier,
    )  # fmt: skip
    if remote is None:
        write_cohort_outputs(out_dir, table, markdown, removed, earlier)
    else:  # temporary keys, copy, read-back digests, marker last (tumor3d.storage.remote_publish)
        done = set(published_names(remote))
        files = cohort_output_files(
            table, markdown, out_dir, name=Path(out_dir).name,
            exists=lambda rel: rel.split("/", 1)[0] in done and remote.exists(rel),
            removed=removed, earlier=earlier,
        )  # fmt: skip
        publish_files(remote, "", files, exclusive=False)
    publish_cohort_artifacts(table, name=Path(out_dir).name)
    for o in outcomes:
        if o.status == STATUS_FAILED:
            logger.warning("patient %s failed at %s: %s", o.patient_id, o.failed_stage, o.error)
    result = CohortResult(
        patients=outcomes, removed=removed, earlier=earlier, out_dir=str(out_dir),
        workers=workers, wall_seconds=wall,
    )  # fmt: skip
    if result.failed:  # Failed in Prefect's UI and API too (as a scheduled run): its result kept
        failed = PatientsFailed(result)
        return Failed(message=str(failed), data=failed)
    return result


def _default_store(out_dir: str | Path) -> str | Path:
    """``DIR/.tumor3d-store``, or ``<url>/.tumor3d-store`` for an object-store ``--out``."""
    return default_store_location(out_dir)


def check_cohort_rows(
    rows: list[ManifestRow], out_dir: str | Path, layout: str = "default"
) -> None:
    """The checks :func:`run_cohort` makes of its rows before any work.

    Ids, folders over inputs, the BIDS labels: for a caller that wants them first (the
    command line, before it starts a Prefect server).
    """
    out = None if is_url(out_dir) else Path(out_dir)
    validate_rows([_row_dict(r) for r in rows], out, bids.check_layout(layout))


def run_cohort(
    manifest: str | Path | list[ManifestRow],
    out_dir: str | Path,
    *,
    config: dict[str, Any] | None = None,
    workers: int | None = None,
    store_dir: str | Path | None = None,
    max_voxels: int = MAX_VOXELS_DEFAULT,
    dask: DaskSpec | None = None,
    layout: str = "default",
) -> CohortResult:
    """Run :func:`cohort_flow` on a manifest CSV or a list of rows.

    Parameters
    ----------
    manifest : path or list of ManifestRow
        Read with :func:`tumor3d.storage.manifest.read_manifest` when a path (a row
        whose image is absent is kept and fails alone).
    out_dir : path
        ``DIR``.
    config : dict, optional
        Pipeline configuration (validated first).
    workers : int, optional
        Stages at a time (``workers +`` :data:`EXTRA_LANES` patients in
        flight); default :func:`default_workers`, or with Dask the cluster's
        number of workers.
    store_dir : path, optional
        Shared artifact store; default ``DIR/.tumor3d-store``.
    max_voxels : int
        Refuse an input whose header declares more voxels (that row fails).
    dask : DaskSpec, optional
        Run the stages on a Dask cluster (:mod:`tumor3d.flows.dask_runner`) instead of
        the default local threads.
    layout : {"default", "bids"}
        ``"bids"``: BIDS derivatives (:mod:`tumor3d.storage.bids`); every patient id
        must give a valid, distinct participant label (checked before any work).

    Raises
    ------
    InputError
        An invalid manifest or configuration, or an output folder holding an
        input (before any work).
    ClusterError
        A Dask scheduler that does not answer (before any work).
    StoreError
        An object store whose endpoint, bucket or credentials do not work
        (before any work).
    FolderBusyError
        Another cohort command is writing the local ``DIR``
        (:mod:`tumor3d.storage.folder_lock`; before any work).
    OSError
        A local ``DIR`` that cannot be made or written (before any work).
    """
    rows_in = (
        read_manifest(manifest, require_files=False)
        if isinstance(manifest, str | Path)
        else list(manifest)
    )
    rows = [_row_dict(r) for r in rows_in]
    cfg = as_config(config)
    if workers is not None and (
        isinstance(workers, bool) or not isinstance(workers, int) or workers < 1
    ):
        raise InputError(f"workers must be an integer >= 1, got {workers!r}")
    out: str | Path = str(out_dir).rstrip("/") if is_url(out_dir) else Path(out_dir)
    validate_rows(rows, None if isinstance(out, str) else out, bids.check_layout(layout))
    if isinstance(out, str):
        RemoteFolder(out).check()  # one line naming the URL, before any patient starts
    store_at = _default_store(out) if store_dir is None else store_dir
    if is_url(store_at):
        store = open_store(str(store_at))
        assert isinstance(store, ObjectStore)
        store.check()  # one line naming the URL, before any patient starts
    n = default_workers() if workers is None else workers
    if dask is not None and dask.address:
        n_cluster = check_scheduler(dask.address)  # one line, before any patient starts
        n = max(1, n_cluster) if workers is None else workers
        # every worker reads the store where this process writes it and runs this code
        check_workers(dask.address, store_at)
    elif dask is not None and dask.n_workers and workers is None:
        n = dask.n_workers
    writer: contextlib.AbstractContextManager[None] = contextlib.nullcontext()
    if isinstance(out, Path):
        check_writable_dir(out)  # an unwritable DIR named before any patient starts
        writer = writing_folder(out)  # one cohort command writes DIR at a time
    flow_fn = cohort_flow.with_options(task_runner=cohort_task_runner(n, dask))
    # the background server, when a Python caller configured none (flows.api_use)
    with writer, api_of_python_call(), tags(f"config:{config_digest(cfg)[:12]}", "cohort"):
        state = flow_fn(
            rows=[_json_row(r) for r in rows], out_dir=str(out),
            config=cfg.model_dump(mode="json"), workers=n,
            store_dir=None if store_dir is None else str(store_dir), max_voxels=int(max_voxels),
            layout=layout, return_state=True,
        )  # fmt: skip
    # a run with failed patients ends Failed, holding its CohortResult; an error, its exception
    result = state.result(raise_on_failure=False)
    if isinstance(result, PatientsFailed):
        return result.result
    if isinstance(result, BaseException):
        raise result
    return result
