"""The evaluation report lists the notes each run said about its own result.

A minimal report (one case, two configurations, no metrics) is enough: the
notes section must name each run's notes once, under its case and
configuration, and leave out runs that failed or said nothing.
"""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd

from tumor3d.storage.evaluation_report import write_report

NOTE = "tumour on the last slice of the scan (slice 3, 0-based): it may continue"


def _prepared(pid: str) -> SimpleNamespace:
    source = SimpleNamespace(
        patient_id=pid, modality="flair", image=Path("/nonexistent") / f"{pid}.nii.gz",
        reference=None,
    )  # fmt: skip
    return SimpleNamespace(
        source=source, reference_kind="expert", acquisition="native", emulation=None
    )


def _report(tmp_path: Path, rows: list[dict]) -> str:
    configs = {"default": {}, "peer": {}}
    path = write_report(
        tmp_path, pd.DataFrame(rows), pd.DataFrame(), configs=configs,
        config_files=dict.fromkeys(configs), prepared=[_prepared("a"), _prepared("b")],
        skipped=[], evaluations={}, command="pytest", elapsed_s=1.0,
    )  # fmt: skip
    return path.read_text()


def test_each_note_is_listed_once_per_configuration_with_the_cases_that_said_it(tmp_path):
    other = "no tumour found: no mesh and no render written"
    text = _report(tmp_path, [
        {"config": "default", "patient_id": "a", "status": "ok", "notes": f"{other}; {NOTE}"},
        {"config": "default", "patient_id": "b", "status": "ok", "notes": other},
        {"config": "peer", "patient_id": "a", "status": "ok", "notes": ""},
        {"config": "peer", "patient_id": "b", "status": "ok", "notes": np.nan},
    ])  # fmt: skip
    assert "Notes of the runs" in text
    assert text.count(f"- default, a, b: {other}") == 1
    assert text.count(f"- default, a: {NOTE}") == 1
    assert "- peer" not in text  # said nothing, or no value


def test_a_failed_runs_notes_are_not_listed(tmp_path):
    text = _report(tmp_path, [
        {"config": "default", "patient_id": "a", "status": "ok", "notes": NOTE},
        {"config": "default", "patient_id": "b", "status": "failed", "notes": "half a run"},
    ])  # fmt: skip
    assert "half a run" not in text and f"- default, a: {NOTE}" in text


def test_no_notes_section_when_no_run_said_anything(tmp_path):
    text = _report(tmp_path, [
        {"config": "default", "patient_id": "a", "status": "ok", "notes": ""},
        {"config": "peer", "patient_id": "a", "status": "ok"},
    ])  # fmt: skip
    assert "Notes of the runs" not in text


def test_cases_show_the_runs_own_status_and_the_flagged_share_of_bad_and_good_volumes(tmp_path):
    """The cases table says a run's own ok / check (was "ok" for every evaluated run, a
    check among them), a failed run with its error; "When to check" counts, per
    configuration, the volumes off by > 25 % and within 10 % that the status flagged,
    leaving out a tumour-free reference (no % error)."""

    def row(cfg, pid, run_status, err, ref_mm3=1000.0):
        return {"config": cfg, "patient_id": pid, "status": "ok", "run_status": run_status,
                "ref_volume_mm3": ref_mm3, "volume_eq7_mm3": 1000.0 * (1 + err / 100),
                "volume_eq7_error_percent": err if ref_mm3 else float("inf")}  # fmt: skip

    text = _report(tmp_path, [
        row("default", "a", "check", -40.0), row("default", "b", "ok", 5.0),
        row("peer", "a", "ok", 30.0),
        {"config": "peer", "patient_id": "b", "status": "failed",
         "error": "InputError: no brain", "run_status": "failed"},
        row("peer", "c", "check", 20.0, ref_mm3=0.0),
    ])  # fmt: skip
    cases = text.split("## Cases")[1].split("## Table 2")[0]
    assert "| a | " in cases and "default: check, peer: ok" in cases
    assert "default: ok, peer: failed (InputError: no brain)" in cases
    assert ("- default: 1 of the 1 volumes off by > 25 % flagged `check`; 0 of the 1 volumes "
            "within 10 % flagged") in cases  # fmt: skip
    assert "- peer: 0 of the 1 volumes off by > 25 % flagged `check`; none within 10 %" in cases


def test_a_review_reason_that_is_no_note_is_listed_and_an_evaluation_failure_keeps_the_status(
    tmp_path,
):
    """Why a run is ``check`` when its segmentation's review says so (those reasons are
    not among its notes): listed beside the notes, once; a run whose comparison with the
    reference failed keeps its own status in the cases table."""
    caveat = "tumour on the last slice of the scan"
    text = _report(tmp_path, [
        {"config": "default", "patient_id": "a", "status": "ok", "run_status": "check",
         "notes": caveat, "review_reasons": f"{caveat}; mean probability 0.70 below 0.85"},
        {"config": "default", "patient_id": "b", "status": "failed", "run_status": "ok",
         "error": "ValueError: no label"},
    ])  # fmt: skip
    assert "- default, a: review: mean probability 0.70 below 0.85" in text
    assert f"review: {caveat}" not in text and f"- default, a: {caveat}" in text
    assert "default: ok (evaluation failed: ValueError: no label)" in text
