"""Prefect artifacts: the patient summary and the cohort table land on their flow run."""

from __future__ import annotations

import json
import re

import pandas as pd
import pytest
from prefect import flow
from prefect.client.orchestration import get_client
from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterFlowRunId
from prefect.runtime import flow_run

from tumor3d.flows.artifacts import (
    artifact_key,
    publish_cohort_artifacts,
    publish_patient_artifacts,
)

pytestmark = pytest.mark.usefixtures("prefect_harness")

KEY = re.compile(r"^[a-z0-9]+(-[a-z0-9]+)*$")


def artifacts_of(flow_run_id):
    """Every artifact of one flow run, by key."""
    with get_client(sync_client=True) as client:
        found = client.read_artifacts(
            artifact_filter=ArtifactFilter(flow_run_id=ArtifactFilterFlowRunId(any_=[flow_run_id]))
        )
    return {a.key: a for a in found}


REPORT = {
    "patient_id": "Pat_01",
    "status": "ok",
    "volumes_mm3": {"eq7": 12345.6, "voxel": 12000.0, "mesh": 11890.25},
    "eq7_precision": {"ce": 0.04, "ci95_low_mm3": 11377.8, "ci95_high_mm3": 13313.4},
    "n_slices": 24,
    "abnormal_slices": [9, 10, 11],
    "stage_seconds": {"segment-tumor": 1.25},
}


@flow(name="t3d-artifact-test-patient")
def _patient_flow(report):
    publish_patient_artifacts(report)
    return str(flow_run.id)


@flow(name="t3d-artifact-test-cohort")
def _cohort_flow(table):
    publish_cohort_artifacts(table, name="My_Cohort")
    return str(flow_run.id)


def test_artifact_keys_are_valid_and_distinct():
    keys = {artifact_key("tumor3d", pid, "summary") for pid in ("Pat_01", "pat-01", "pat.01")}
    assert len(keys) == 3
    assert all(KEY.match(k) for k in keys)
    assert artifact_key("tumor3d", "pat-0003", "table") == "tumor3d-pat-0003-table"


def test_patient_summary_artifacts_on_the_flow_run():
    run_id = _patient_flow(REPORT)
    arts = artifacts_of(run_id)
    md_key = artifact_key("tumor3d", "Pat_01", "summary")
    table_key = artifact_key("tumor3d", "Pat_01", "table")
    assert set(arts) == {md_key, table_key}
    assert arts[md_key].type == "markdown" and arts[table_key].type == "table"
    md = arts[md_key].data
    assert "| Eq. 7 (slab sum) | 12,345.6 | 12.346 |" in md
    assert "95 % interval 11,377.8 to 13,313.4 mm³" in md
    rows = arts[table_key].data
    rows = json.loads(rows) if isinstance(rows, str) else rows
    table = {(r["quantity"], r["unit"]): r["value"] for r in rows}
    assert table[("volume, Voxel count", "mL")] == "12.000"
    assert table[("abnormal slices", "")] == "3"


def test_cohort_table_artifact_on_the_flow_run():
    table = pd.DataFrame(
        [
            {"patient_id": "a", "status": "ok", "failed_stage": None, "error": None,
             "volume_eq7_mm3": 1500.0, "volume_eq7_ml": 1.5, "n_slices": 20},
            {"patient_id": "b", "status": "failed", "failed_stage": "prepare-input",
             "error": "InputError: no such file", "volume_eq7_mm3": float("nan"),
             "volume_eq7_ml": float("nan"), "n_slices": float("nan")},
        ]
    )  # fmt: skip
    run_id = _cohort_flow(table)
    arts = artifacts_of(run_id)
    key = artifact_key("tumor3d", "cohort", "My_Cohort")
    assert list(arts) == [key] and arts[key].type == "table"
    rows = arts[key].data
    rows = json.loads(rows) if isinstance(rows, str) else rows
    assert [r["patient_id"] for r in rows] == ["a", "b"]
    assert rows[0]["volume_eq7_ml"] == 1.5 and rows[1]["volume_eq7_mm3"] is None
    assert rows[1]["failed_stage"] == "prepare-input"
