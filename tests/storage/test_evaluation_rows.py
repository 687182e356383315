"""The rows of ``evaluation.parquet`` and ``evaluation_slices.parquet``, shaped in storage.

Issue 31 item 2: the evaluation flow only wires; :mod:`tumor3d.storage.evaluation_tables`
gathers the manifests' rows, shapes each case's rows from its run and the evaluations,
and writes both tables. Here without a flow: outcomes stand in for the cohort's, and
``load_case`` for the published files.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

import tumor3d.storage.evaluation_tables as evaluation_tables
from tumor3d.evaluation import EvaluationRows
from tumor3d.evaluation.registry import Evaluation
from tumor3d.storage.evaluation_tables import collect_rows, evaluation_rows, write_evaluation_tables

REVIEW = ("needs_review", "review_reasons", "segmentation_quality_score")


def _prepared(pid: str) -> SimpleNamespace:
    source = SimpleNamespace(patient_id=pid, modality="t2", image=Path(f"/in/{pid}.nii.gz"))
    return SimpleNamespace(source=source, reference_kind="truth", acquisition="native, 5 mm")


def _outcome(pid: str, status: str = "ok", **metrics) -> SimpleNamespace:
    failed = status == "failed"
    return SimpleNamespace(
        patient_id=pid, status=status, failed_stage="segment" if failed else None,
        error="InputError: no brain" if failed else None,
        output_dir=None if failed else f"/out/{pid}", metrics=metrics,
    )  # fmt: skip


def _evaluation(name: str, fn) -> Evaluation:
    return Evaluation(name, "unit test", fn)


def _counts(case) -> EvaluationRows:
    return EvaluationRows(patient={"count": case.n}, slices=[{"slice_index": 0, "v": case.n}])


@pytest.fixture
def loaded(monkeypatch):
    """``load_case`` without files: the case of a patient is its output folder's name."""
    monkeypatch.setattr(evaluation_tables, "load_case",
                        lambda p, out: SimpleNamespace(n=len(Path(out).name)))  # fmt: skip


def test_a_row_is_the_case_its_run_its_published_values_then_the_evaluations(loaded):
    metrics = {"volume_eq7_mm3": 1000.0, "n_slices": 4, "notes": None, "needs_review": False,
               "review_reasons": "", "voxel_size_mm": 1.0, "status": "ok"}  # fmt: skip
    patients, slices = evaluation_rows(
        "default", [_prepared("p1")], [_outcome("p1", **metrics)],
        {"count": _evaluation("count", _counts)}, review_columns=REVIEW,
    )  # fmt: skip
    assert patients == [{
        "config": "default", "patient_id": "p1", "group": "truth, native, 5 mm",
        "reference_kind": "truth", "acquisition": "native, 5 mm", "modality": "t2",
        "image": "p1.nii.gz", "status": "ok", "run_status": "ok", "failed_stage": None,
        "error": None, "volume_eq7_mm3": 1000.0, "n_slices": 4, "notes": "",
        "needs_review": False, "review_reasons": "", "count": 2,
    }]  # fmt: skip
    assert list(patients[0])[-6:] == ["volume_eq7_mm3", "n_slices", "notes", "needs_review",
                                      "review_reasons", "count"]  # fmt: skip
    assert slices == [{"config": "default", "patient_id": "p1", "evaluation": "count",
                       "slice_index": 0, "v": 2}]  # fmt: skip


def test_a_failed_or_missing_run_keeps_only_the_case_and_why(loaded):
    patients, slices = evaluation_rows(
        "peer", [_prepared("p1"), _prepared("p2")], [_outcome("p1", "failed", n_slices=4)],
        {"count": _evaluation("count", _counts)},
    )  # fmt: skip
    assert slices == []
    failed, missing = patients
    assert (failed["status"], failed["run_status"], failed["failed_stage"]) == (
        "failed", "failed", "segment")  # fmt: skip
    assert failed["error"] == "InputError: no brain" and "n_slices" not in failed
    assert (missing["status"], missing["run_status"], missing["error"]) == (
        "failed", "failed", "not run")  # fmt: skip
    assert missing["failed_stage"] is None and "count" not in missing


def test_a_failing_evaluation_fails_its_case_only_keeping_the_evaluations_before(loaded):
    def broken(case):
        raise ValueError("boom\nsecond line")

    evaluations = {"count": _evaluation("count", _counts), "broken": _evaluation("broken", broken)}
    patients, slices = evaluation_rows(
        "default", [_prepared("p1"), _prepared("p22")],
        [_outcome("p1", "check"), _outcome("p22")], evaluations,
    )  # fmt: skip
    assert [(p["status"], p["run_status"], p["failed_stage"], p["error"]) for p in patients] == [
        ("failed", "check", "evaluate", "ValueError: boom"),
        ("failed", "ok", "evaluate", "ValueError: boom"),
    ]
    assert [p["count"] for p in patients] == [2, 3]  # the first evaluation's, kept
    assert [s["patient_id"] for s in slices] == ["p1", "p22"]


def test_the_tables_are_written_parquet_safe_and_returned_as_built(tmp_path):
    patients = [
        {"config": "default", "patient_id": "p1", "needs_review": True, "n": 1, "mixed": 1},
        {"config": "default", "patient_id": "p2", "needs_review": None, "n": None, "mixed": "x"},
    ]
    got, slices = write_evaluation_tables(tmp_path, patients, [])
    assert got["mixed"].tolist() == [1, "x"] and slices.empty
    schema = pq.read_schema(tmp_path / "evaluation.parquet")
    assert schema.field("needs_review").type == pa.bool_()  # not text: parquet_safe
    assert schema.field("n").type == pa.float64()
    back = pd.read_parquet(tmp_path / "evaluation.parquet")
    assert back["n"].isna().tolist() == [False, True] and back["mixed"].tolist() == ["1", "x"]
    assert pd.read_parquet(tmp_path / "evaluation_slices.parquet").empty


def _manifest(path: Path, *pids: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    lines = ["patient_id,image,modality"]
    for pid in pids:
        (path.parent / f"{pid}.nii.gz").write_bytes(b"")
        lines.append(f"{pid},{pid}.nii.gz,t2")
    path.write_text("\n".join(lines) + "\n")
    return path


def test_rows_of_several_manifests_skip_a_patient_id_given_before(tmp_path):
    first = _manifest(tmp_path / "a" / "m.csv", "p1", "p2")
    second = _manifest(tmp_path / "b" / "m.csv", "p2", "p3")
    with open(second, "a") as fh:
        fh.write("p4,absent.nii.gz,t2\n")
    rows, skipped = collect_rows([first, second])
    assert [r.patient_id for r in rows] == ["p1", "p2", "p3"]
    assert [(s["patient_id"], s["missing_file"]) for s in skipped] == [("p4", True),
                                                                       ("p2", False)]  # fmt: skip
    assert skipped[0]["row"] == 3 and skipped[1]["row"] is None
    assert skipped[1]["reason"] == f"{second}: duplicate patient_id 'p2' (also in {first})"
