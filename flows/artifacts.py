"""Prefect artifacts: the patient's summary and the cohort table on their flow runs.

The Prefect UI then shows, on the run itself, what ``report.html`` and
``cohort.html`` show on disk: a markdown artifact (volumes in mm3 and mL
with their definitions and the Eq. 7 interval, slices, faces, time per
stage) and a table artifact with the same numbers, one row per quantity;
for a cohort, a table with one row per patient. The content comes from the
same builders as the pages (:mod:`tumor3d.storage.report_html`), so the numbers
agree. Must be called inside a flow run (artifacts attach to the current run).

Artifact keys (:func:`artifact_key`) hold only lowercase letters, digits and
dashes, as Prefect requires: ``tumor3d-<patient>-summary``,
``tumor3d-<patient>-table``, ``tumor3d-cohort-<name>``. A patient id that
is not already of that form (``Pat_01``) is lower-cased, other characters
become dashes, and 8 hex digits of its SHA-256 are appended, so two ids
never share a key.
"""

from __future__ import annotations

import hashlib
import math
import re
from collections.abc import Mapping
from typing import Any
from uuid import UUID

import pandas as pd
from prefect.artifacts import create_markdown_artifact, create_table_artifact

from tumor3d.storage.report_html import patient_report_markdown, patient_summary_table

__all__ = ["artifact_key", "publish_cohort_artifacts", "publish_patient_artifacts"]

_KEY_OK = re.compile(r"^[a-z0-9]+(-[a-z0-9]+)*$")

#: Cohort table columns (those present are shown, in this order).
_COHORT_COLUMNS = (
    "patient_id", "status", "review_reasons", "failed_stage", "error",
    "volume_eq7_mm3", "volume_eq7_ml", "volume_eq7_ci95_low_mm3", "volume_eq7_ci95_high_mm3",
    "volume_voxel_mm3", "volume_voxel_ml", "volume_mesh_mm3", "volume_mesh_ml",
    "volume_mesh_simplified_mm3", "n_slices", "n_abnormal_slices", "faces_mc",
    "faces_simplified", "time_flow_s",
)  # fmt: skip


def artifact_key(*parts: str) -> str:
    """A valid Prefect artifact key from ``parts`` (joined with dashes).

    >>> artifact_key("tumor3d", "pat-0003", "summary")
    'tumor3d-pat-0003-summary'
    >>> artifact_key("tumor3d", "Pat_01", "summary")
    'tumor3d-pat-01-97ea08c3-summary'
    """
    out = []
    for part in parts:
        text = str(part)
        clean = re.sub(r"[^a-z0-9]+", "-", text.lower()).strip("-") or "x"
        if clean != text:
            clean = f"{clean}-{hashlib.sha256(text.encode()).hexdigest()[:8]}"
        out.append(clean)
    key = "-".join(out)
    assert _KEY_OK.match(key), key
    return key


def publish_patient_artifacts(report: Mapping[str, Any]) -> tuple[UUID, UUID]:
    """The markdown summary and the table of one patient on the current flow run.

    Parameters
    ----------
    report : mapping
        The report content (``PatientResult.report``).

    Returns
    -------
    (UUID, UUID)
        The ids of the markdown and the table artifact.
    """
    pid = str(report["patient_id"])
    md = create_markdown_artifact(
        markdown=patient_report_markdown(report),
        key=artifact_key("tumor3d", pid, "summary"),
        description=f"tumor3d summary of patient {pid}: volumes, slices, faces, time per stage",
    )
    table = create_table_artifact(
        table=patient_summary_table(report),
        key=artifact_key("tumor3d", pid, "table"),
        description=f"tumor3d measurements of patient {pid}",
    )
    return md, table


def _cell(value: Any) -> Any:
    if value is None or isinstance(value, (bool, int, str)):
        return value
    if isinstance(value, float):
        return None if math.isnan(value) else round(value, 4)
    try:
        f = float(value)
    except (TypeError, ValueError):
        return str(value)
    return None if math.isnan(f) else round(f, 4)


def publish_cohort_artifacts(table: pd.DataFrame, *, name: str) -> UUID:
    """The cohort table (one row per patient) on the current flow run.

    Parameters
    ----------
    table : DataFrame
        ``cohort.parquet``'s table (:func:`tumor3d.storage.cohort_report.cohort_table`).
    name : str
        The cohort's name (its output folder's name), part of the key.
    """
    cols = [c for c in _COHORT_COLUMNS if c in table.columns]
    rows = [{c: _cell(r[c]) for c in cols} for r in table[cols].to_dict(orient="records")]
    return create_table_artifact(
        table=rows,
        key=artifact_key("tumor3d", "cohort", name),
        description=f"tumor3d cohort {name}: {len(rows)} patient(s), volumes and status",
    )
