"""The tables of an evaluation: its cases gathered, its rows shaped, its parquet written.

* :func:`collect_rows` and :func:`prepare_cases` gather the rows of the manifests
  (and of generated phantoms) that can be evaluated, and the skipped ones with why;
* :func:`evaluation_rows` turns one configuration's run into the rows of
  ``evaluation.parquet`` (the case, the run's status, its volumes and counts, notes
  and review columns, then every evaluation's columns) and
  ``evaluation_slices.parquet``, and :func:`write_evaluation_tables` writes both.

The files of one case (the emulated input, the reference, the published outputs)
are read by :mod:`tumor3d.storage.evaluation_io`.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import pandas as pd

from tumor3d.errors import InputError
from tumor3d.evaluation.registry import Evaluation
from tumor3d.storage.atomic import atomic_write_bytes
from tumor3d.storage.evaluation_io import PreparedCase, load_case, prepare_case
from tumor3d.storage.formats import encode_parquet
from tumor3d.storage.manifest import ManifestRow, RowProblem, read_manifest_rows

__all__ = [
    "COPIED_METRICS_PREFIXES",
    "RunOutcome",
    "collect_rows",
    "evaluation_rows",
    "parquet_safe",
    "prepare_cases",
    "write_evaluation_tables",
]

#: ``metrics.parquet`` columns an ``evaluation.parquet`` row copies (volumes, counts).
COPIED_METRICS_PREFIXES = ("volume_", "n_")


def skip_record(
    patient_id: str | None, reason: str, missing_file: bool, problem: RowProblem | None = None
) -> dict[str, Any]:
    """A row not evaluated, as the evaluation flow's ``skipped`` lists it.

    ``patient_id``, ``row`` (of its manifest, when a manifest refused it), ``reason``
    and ``missing_file`` (whether only a file was absent).
    """
    return {
        "patient_id": patient_id,
        "row": None if problem is None else problem.row,
        "reason": reason,
        "missing_file": bool(missing_file),
    }


def phantom_rows(n: int, folder: Path) -> list[ManifestRow]:
    """Generate phantoms ``phantom000``.. (seeds 0..n-1) in ``folder``, truth as reference."""
    from tumor3d.phantom import make_phantom_patient
    from tumor3d.storage.phantom_io import write_phantom_cohort

    patients = [make_phantom_patient(seed, patient_id=f"phantom{seed:03d}") for seed in range(n)]
    manifest = write_phantom_cohort(patients, folder)
    rows, problems = read_manifest_rows(manifest)
    if problems:  # pragma: no cover - we wrote it ourselves
        raise InputError(problems[0].message)
    return [replace(r, reference_kind="truth") for r in rows]


def collect_rows(
    manifests: Iterable[str | Path], phantoms: int = 0, phantom_dir: str | Path = "phantoms"
) -> tuple[list[ManifestRow], list[dict[str, Any]]]:
    """The rows of the manifests (read leniently) and of generated phantoms.

    Parameters
    ----------
    manifests : iterable of path
        Cohort manifests, read in order.
    phantoms : int, default 0
        Also generate this many phantoms (:func:`phantom_rows`) in ``phantom_dir``.

    Returns
    -------
    rows : list of ManifestRow
        The good rows, in order.
    skipped : list of dict
        :func:`skip_record` of each manifest's bad rows, then of every row whose
        ``patient_id`` came before.

    Raises
    ------
    InputError
        A manifest that cannot be read as a whole.
    """
    skipped: list[dict[str, Any]] = []
    sources: list[tuple[str, list[ManifestRow]]] = []
    for m in manifests:
        good, problems = read_manifest_rows(m)
        sources.append((str(m), good))
        skipped += [skip_record(q.patient_id, q.message, q.missing_file, q) for q in problems]
    if phantoms:
        generated = phantom_rows(phantoms, Path(phantom_dir))
        sources.append((f"{phantoms} generated phantoms", generated))
    rows: list[ManifestRow] = []
    seen: dict[str, str] = {}
    for where, good in sources:
        for r in good:
            pid = r.patient_id
            if pid in seen:
                why = f"{where}: duplicate patient_id {pid!r} (also in {seen[pid]})"
                skipped.append(skip_record(pid, why, False))
                continue
            seen[pid] = where
            rows.append(r)
    return rows, skipped


def prepare_cases(
    rows: Iterable[ManifestRow], work_dir: str | Path
) -> tuple[list[PreparedCase], list[dict[str, Any]]]:
    """:func:`prepare_case` of each row: the prepared ones, and the rows it refused."""
    prepared: list[PreparedCase] = []
    skipped: list[dict[str, Any]] = []
    for r in rows:
        try:
            prepared.append(prepare_case(r, work_dir))
        except InputError as exc:
            skipped.append(skip_record(r.patient_id, str(exc), False))
    return prepared, skipped


class RunOutcome(Protocol):
    """One patient's pipeline run, as the cohort flow reports it (``PatientOutcome``)."""

    patient_id: str
    status: str
    failed_stage: str | None
    error: str | None
    output_dir: str | None
    metrics: dict[str, Any]


def _run_row(config: str, prepared: PreparedCase, outcome: RunOutcome | None) -> dict[str, Any]:
    """The case and how its run went: the first columns of ``evaluation.parquet``."""
    o = outcome
    return {
        "config": config, "patient_id": prepared.source.patient_id,
        "group": f"{prepared.reference_kind}, {prepared.acquisition}",
        "reference_kind": prepared.reference_kind, "acquisition": prepared.acquisition,
        "modality": prepared.source.modality, "image": prepared.source.image.name,
        # evaluated or not; the run's own ok/check is run_status
        "status": "failed" if o is None or o.status == "failed" else "ok",
        "run_status": "failed" if o is None else o.status,
        "failed_stage": None if o is None else o.failed_stage,
        "error": "not run" if o is None else o.error,
    }  # fmt: skip


def _published_values(metrics: Mapping[str, Any], review_columns: Sequence[str]) -> dict:
    """What a row copies of ``metrics.parquet``: volumes and counts, notes, when to check."""
    row = {k: v for k, v in metrics.items() if k.startswith(COPIED_METRICS_PREFIXES)}
    row["notes"] = str(metrics.get("notes") or "")
    row.update({k: metrics[k] for k in review_columns if k in metrics})
    return row


def _case_rows(
    config: str,
    prepared: PreparedCase,
    outcome: RunOutcome | None,
    evaluations: Mapping[str, Evaluation],
    review_columns: Sequence[str],
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    """One case's ``evaluation.parquet`` row and ``evaluation_slices.parquet`` rows.

    A failed comparison (reading the outputs or an evaluation) marks the row
    ``failed`` at stage ``evaluate``, keeping the columns of the evaluations before it.
    """
    row = _run_row(config, prepared, outcome)
    slices: list[dict[str, Any]] = []
    if outcome is None or outcome.status == "failed":
        return row, slices
    row.update(_published_values(outcome.metrics, review_columns))
    pid = prepared.source.patient_id
    try:
        case = load_case(prepared, outcome.output_dir)
        for ev in evaluations.values():
            got = ev.fn(case)
            row.update(got.patient)
            slices += [{"config": config, "patient_id": pid, "evaluation": ev.name, **s}
                       for s in got.slices]  # fmt: skip
    except Exception as exc:  # one patient's comparison must not stop the others
        row.update(status="failed", failed_stage="evaluate",
                   error=f"{type(exc).__name__}: {exc}".splitlines()[0])  # fmt: skip
    return row, slices


def evaluation_rows(
    config: str,
    prepared: Sequence[PreparedCase],
    outcomes: Iterable[RunOutcome],
    evaluations: Mapping[str, Evaluation],
    *,
    review_columns: Sequence[str] = (),
) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """One configuration's rows of ``evaluation.parquet`` and ``evaluation_slices.parquet``.

    Parameters
    ----------
    config : str
        The configuration's name.
    prepared : sequence of PreparedCase
        The cases run, in order (one row each).
    outcomes : iterable of RunOutcome
        The cohort's outcomes (by patient id; a case without one was not run).
    evaluations : mapping
        Name -> registered evaluation, run on each case whose run completed.
    review_columns : sequence of str
        ``metrics.parquet``'s columns of when to check, copied when present.

    Returns
    -------
    patients, slices : list of dict
        Per case: the case, its run's status (``status`` ``ok`` once compared),
        the run's volumes and counts (:data:`COPIED_METRICS_PREFIXES`), ``notes``,
        the review columns, then each evaluation's columns; per acquired slice:
        ``config``, ``patient_id``, ``evaluation`` and the evaluation's columns.
    """
    by_id = {o.patient_id: o for o in outcomes}
    patients: list[dict[str, Any]] = []
    slices: list[dict[str, Any]] = []
    for p in prepared:
        row, rows = _case_rows(
            config, p, by_id.get(p.source.patient_id), evaluations, review_columns
        )
        patients.append(row)
        slices += rows
    return patients, slices


def write_evaluation_tables(
    out_dir: str | Path, patients: list[dict[str, Any]], slices: list[dict[str, Any]]
) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Write ``evaluation.parquet`` and ``evaluation_slices.parquet``; return their tables.

    The tables are returned as built from the rows (before :func:`parquet_safe`).
    """
    out = Path(out_dir)
    tables = pd.DataFrame(patients), pd.DataFrame(slices)
    for name, table in zip(("evaluation", "evaluation_slices"), tables, strict=True):
        atomic_write_bytes(out / f"{name}.parquet", encode_parquet(parquet_safe(table)))
    return tables


def parquet_safe(df: pd.DataFrame) -> pd.DataFrame:
    """Object columns holding mixed None/bool/number become parquet-friendly.

    All booleans: nullable ``boolean``; all numbers: numeric (None as NaN); else text
    (None kept).

    >>> df = pd.DataFrame({"a": [True, None], "b": [1, None], "c": [1, "x"]}, dtype=object)
    >>> out = parquet_safe(df)
    >>> str(out["a"].dtype), str(out["b"].dtype), out["c"].tolist()
    ('boolean', 'float64', ['1', 'x'])
    """
    out = df.copy()
    for c in out.columns:
        if out[c].dtype == object:
            values = [v for v in out[c] if v is not None and not _is_nan(v)]
            if values and all(isinstance(v, bool | np.bool_) for v in values):
                out[c] = out[c].astype("boolean")
            elif values and all(isinstance(v, int | float | np.number) for v in values):
                out[c] = pd.to_numeric(out[c], errors="coerce")
            else:
                out[c] = out[c].map(lambda v: None if v is None else str(v))
    return out


def _is_nan(v: Any) -> bool:
    return isinstance(v, float) and np.isnan(v)
