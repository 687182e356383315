"""A patient failed for the machine (a full disk, a store) is told from one failed for its
input: its one-line error names the file, and the cohort's exit code is 3, not 1, so that a
scheduled job can tell "disk full" from "bad scan"."""

from __future__ import annotations

import errno

import pytest
from phantom_rows import small_phantom_rows

import tumor3d.flows.cohort as cohort
from tumor3d.flows.cohort import _run_one
from tumor3d.flows.cohort_result import CohortResult, PatientOutcome
from tumor3d.storage.store import ArtifactStore


def _fail_with(monkeypatch, exc: BaseException) -> None:
    def pipeline(*args, **kwargs):
        raise exc

    monkeypatch.setattr(cohort, "patient_pipeline", pipeline)


@pytest.mark.parametrize(
    ("exc", "environment", "error"),
    [
        (OSError(errno.ENOSPC, "No space left on device", "out/p/mesh.ply"), True,
         "OSError: out/p/mesh.ply: no space left on device (ENOSPC)"),
        (OSError(errno.EACCES, "Permission denied", "out/p"), True,
         "PermissionError: out/p: permission denied (EACCES)"),
        (ValueError("the mesh has no faces"), False, "ValueError: the mesh has no faces"),
    ],
)  # fmt: skip
def test_a_failure_of_the_machine_is_marked_and_names_its_file(
    monkeypatch, tmp_path, exc, environment, error
):
    row = small_phantom_rows(tmp_path / "in", [0], "env")[0]
    _fail_with(monkeypatch, exc)
    store = ArtifactStore(tmp_path / "store")
    out = _run_one(cohort._row_dict(row), str(tmp_path / "out"), cohort.parse_config({}), store)
    assert out.status == "failed" and out.environment is environment
    assert out.error == error


def test_an_unreadable_input_is_the_inputs_failure_not_the_machines(monkeypatch, tmp_path):
    """Permission denied while the input is read (before any stage) is the input's problem."""
    row = small_phantom_rows(tmp_path / "in", [0], "env")[0]

    def unreadable(path, **kwargs):
        raise PermissionError(errno.EACCES, "Permission denied", str(path))

    monkeypatch.setattr(cohort, "prepare_source", unreadable)
    out = _run_one(
        cohort._row_dict(row), str(tmp_path / "out"), cohort.parse_config({}),
        ArtifactStore(tmp_path / "store"),
    )  # fmt: skip
    assert out.status == "failed" and out.failed_stage == "prepare-input"
    assert not out.environment
    assert out.error == f"PermissionError: {row.image}: permission denied (EACCES)"


def test_the_exit_code_is_3_when_some_patient_failed_for_the_machine():
    ok = PatientOutcome(patient_id="a", status="ok")
    bad_input = PatientOutcome(patient_id="b", status="failed", error="InputError: x")
    full = PatientOutcome(patient_id="c", status="failed", error="OSError: d", environment=True)
    check = PatientOutcome(patient_id="d", status="check")
    assert CohortResult(patients=[ok, check]).exit_code == 4
    assert CohortResult(patients=[ok, bad_input, check]).exit_code == 1
    assert CohortResult(patients=[ok, bad_input, full]).exit_code == 3
