"""The report's table per case and summary per group show what the evaluations declare.

Issue 31 item 4: the columns, labels and formats come from the evaluation registry
(:class:`tumor3d.evaluation.registry.ReportColumns`), not from the report's code: a fake
evaluation's declared columns appear, and the segmentation's tables follow its
declaration.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace

import pandas as pd

from tumor3d.evaluation import EvaluationRows, registered_evaluations
from tumor3d.evaluation.registry import Evaluation, ReportColumn, ReportColumns
from tumor3d.storage.evaluation_report import write_report

FAKE = Evaluation(
    "unit-fake",
    "scores every case",
    lambda case: EvaluationRows(),
    columns=ReportColumns(
        title="Fake scores",
        intro="Per configuration: the fake score and its rank.",
        table=(ReportColumn("score / rank", ("fake_score", "fake_rank"), "{:.2f}"),),
        summary=(ReportColumn("mean score", ("fake_score",), "{:.1f}"),),
    ),
)


def _prepared(pid: str) -> SimpleNamespace:
    source = SimpleNamespace(
        patient_id=pid, modality="t2", image=Path("/nonexistent") / f"{pid}.nii.gz",
        reference=None,
    )  # fmt: skip
    return SimpleNamespace(source=source, reference_kind="truth", acquisition="native",
                           emulation=None)  # fmt: skip


def _report(tmp_path: Path, rows: list[dict], evaluations: dict) -> str:
    configs = {"default": {}, "peer": {}}
    path = write_report(
        tmp_path, pd.DataFrame(rows), pd.DataFrame(), configs=configs,
        config_files=dict.fromkeys(configs), prepared=[_prepared("a"), _prepared("b")],
        skipped=[], evaluations=evaluations, command="pytest", elapsed_s=1.0,
    )  # fmt: skip
    return path.read_text()


def _section(text: str, heading: str) -> str:
    return text.split(f"## {heading}")[1].split("\n## ")[0]


def test_a_registered_evaluations_declared_columns_make_its_table_and_summary(tmp_path):
    rows = [
        {"config": "default", "patient_id": "a", "status": "ok", "fake_score": 0.5,
         "fake_rank": 1},
        {"config": "default", "patient_id": "b", "status": "ok", "fake_score": 0.25},
        {"config": "peer", "patient_id": "a", "status": "ok", "fake_score": 2.0, "fake_rank": 2},
        {"config": "peer", "patient_id": "b", "status": "failed", "error": "no brain"},
    ]  # fmt: skip
    text = _report(tmp_path, rows, {"unit-fake": FAKE})
    table = _section(text, "Fake scores")
    assert "Per configuration: the fake score and its rank." in table
    assert "| patient | default: score / rank | peer: score / rank |" in table
    assert "| a | 0.50 / 1.00 | 2.00 / 2.00 |" in table
    assert "| b | 0.25 / – | – / – |" in table
    summary = _section(text, "Summary per group")
    assert "| group | configuration | n ok | mean score |" in summary
    assert "| truth, native, t2 | default | 2/2 | 0.4 |" in summary
    assert "| truth, native, t2 | peer | 1/2 | 2.0 |" in summary
    # the segmentation's own tables belong to the segmentation evaluation
    assert "## Table 2" not in text and "## Overlap and surface distance" not in text


def test_no_summary_without_declared_summary_columns(tmp_path):
    quiet = replace(FAKE, columns=replace(FAKE.columns, summary=()))
    text = _report(tmp_path, [{"config": "default", "patient_id": "a", "status": "ok"}],
                   {"unit-fake": quiet})  # fmt: skip
    assert "## Fake scores" in text and "## Summary per group" not in text


def test_the_segmentation_tables_follow_its_declaration(tmp_path):
    """Relabel a column and drop one in the segmentation's declaration: the report's
    table per case and summary change with it."""
    seg = registered_evaluations()["segmentation"]
    declared = seg.columns
    relabelled = replace(
        declared,
        table=(ReportColumn("3-D Dice only", ("dice_3d",), "{:.2f}"), *declared.table[1:]),
        summary=declared.summary[:1],
    )
    rows = [{"config": n, "patient_id": p, "status": "ok", "dice_3d": 0.875, "tp": 1, "fn": 0,
             "fp": 0, "tn": 3, "dice_slices_mean": 0.9} for n in ("default", "peer")
            for p in ("a", "b")]  # fmt: skip
    text = _report(tmp_path, rows, {"segmentation": replace(seg, columns=relabelled)})
    overlap = _section(text, "Overlap and surface distance")
    assert "default: 3-D Dice only" in overlap and "| a | 0.88 |" in overlap
    assert "Dice slice / pooled / 3-D" not in overlap
    summary = _section(text, "Summary per group")
    assert summary.splitlines()[2] == "| group | configuration | n ok | ref-slice Dice |"
    # and as declared in the registry, the report's tables as before
    text = _report(tmp_path, rows, {"segmentation": seg})
    assert "| patient | default: Dice slice / pooled / 3-D | default: HD95 / HD (mm) |" in text
    assert (
        "| ref-slice Dice | pooled Dice | 3-D Dice | HD95 (mm) | Eq. 9 (%) | Eq. 7 err. (%) "
        "| mesh err. (%) |" in text
    )
