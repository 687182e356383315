"""The evaluation flow end to end on two phantoms against their own truth."""

from __future__ import annotations

import csv

import pandas as pd
import pytest
from typer.testing import CliRunner

from tumor3d.phantom import make_phantom_patient
from tumor3d.storage.phantom_io import write_phantom_cohort

pytestmark = [pytest.mark.slow]


@pytest.fixture(scope="module")
def evaluated(tmp_path_factory, prefect_harness):
    from tumor3d.flows.evaluate import run_evaluation

    root = tmp_path_factory.mktemp("evalflow")
    patients = [make_phantom_patient(s, patient_id=f"ph{s}") for s in (0, 1)]
    manifest = write_phantom_cohort(patients, root / "in")
    with open(manifest, newline="") as fh:
        rows = list(csv.DictReader(fh))
    # + a row whose image is absent (skipped) and one asking for a label the truth lacks
    absent = dict(rows[0], patient_id="gone", image="nowhere/x.nii.gz")
    nolabel = dict(rows[1], patient_id="nolabel", reference_labels="7")
    with open(manifest, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows([*rows, absent, nolabel])
    out = root / "out"
    result = run_evaluation([manifest], out, command="pytest")
    return result, out


def test_phantoms_match_their_truth(evaluated):
    result, out = evaluated
    df = pd.read_parquet(out / "evaluation.parquet")
    assert sorted(df["patient_id"]) == ["ph0", "ph1"]
    assert (df["status"] == "ok").all()
    assert (df["dice_3d"] > 0.95).all()
    assert (df["dice_pooled"] > 0.95).all()
    assert (df["fn"] == 0).all() and (df["fp"] == 0).all()
    assert (df["hd95_mm"] < 3.0).all()
    assert (df["hd95_surface_mm"] < 3.0).all()  # published mesh vs the truth's surface
    assert (df["volume_eq7_error_percent"].abs() < 5.0).all()
    # each run's notes are kept with its figures (the phantoms' tumours give none)
    assert (df["notes"] == "").all()
    slices = pd.read_parquet(out / "evaluation_slices.parquet")
    n = slices.groupby("patient_id").size()
    assert (n == df.set_index("patient_id")["n_slices"]).all()
    # per-slice rows add up to the patient's pixel counts
    sums = slices.groupby("patient_id")[["n_p", "n_g"]].sum()
    assert (sums["n_g"] == df.set_index("patient_id")["n_g"]).all()


def test_bad_rows_are_reported_and_do_not_stop_the_others(evaluated):
    result, _ = evaluated
    reasons = {s["patient_id"]: s for s in result.skipped}
    assert reasons["gone"]["missing_file"] and "does not exist" in reasons["gone"]["reason"]
    assert not reasons["nolabel"]["missing_file"]
    assert "patient nolabel" in reasons["nolabel"]["reason"]
    assert "none of the requested labels 7" in reasons["nolabel"]["reason"]
    assert result.n_invalid == 1 and result.n_failed == 0


def test_report_has_the_tables_and_plot(evaluated):
    result, out = evaluated
    text = (out / "REPORT.md").read_text()
    for heading in ("## Table 2", "## Table 3", "## Overlap and surface distance", "## Volumes",
                    "## Provenance", "Bland-Altman"):  # fmt: skip
        assert heading in text
    assert "| ph0 |" in text and "gone (file absent)" in text
    # pooled rows are per kind of reference, acquisition and modality (never FLAIR with T1c)
    # (the phantom writer declares its reference: reference_kind truth)
    assert "| truth, native, 5 mm slice step, t2 |" in text
    png = out / "bland_altman_default.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_cli_rejects_a_bad_manifest_and_config_with_exit_2(tmp_path):
    from tumor3d.flows.cli import app

    bad = tmp_path / "m.csv"
    bad.write_text("patient_id,image\n")
    r = CliRunner().invoke(app, ["evaluate", str(bad), "--out", str(tmp_path / "o")])
    assert r.exit_code == 2 and "missing required column" in r.output
    good = tmp_path / "g.csv"
    good.write_text("patient_id,image,modality\np,x.nii.gz,t2\n")
    r = CliRunner().invoke(
        app, ["evaluate", str(good), "--out", str(tmp_path / "o"), "--config", "a=nope.yaml"]
    )
    assert r.exit_code == 2 and "nope.yaml" in r.output


def test_evaluate_has_help():
    from tumor3d.flows.cli import app

    r = CliRunner().invoke(app, ["evaluate", "--help"])
    assert r.exit_code == 0 and "NAME=FILE" in r.output


def test_evaluate_scores_the_phantom_commands_own_manifest(tmp_path, evaluated):
    """Issue 33: `tumor3d phantom` then `tumor3d evaluate` on its manifest (was: exit 1,
    the tumour-free row refused, Tables 2 and 3 without a row). The store is the first
    evaluation's: phantom000 is its ph0 (seed 0), so only the ingest stage reads it again
    (its file name is in the key); the tumour-free phantom001n is computed."""
    from tumor3d.flows.cli import app

    _, first_out = evaluated
    runner = CliRunner()
    made = runner.invoke(app, ["phantom", "--out", str(tmp_path / "ph"), "--n", "2",
                               "--normal", "1"])  # fmt: skip
    assert made.exit_code == 0, made.output
    res = runner.invoke(app, ["evaluate", str(tmp_path / "ph" / "manifest.csv"),
                              "--out", str(tmp_path / "ev"), "--workers", "2",
                              "--store", str(first_out / ".tumor3d-store")])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert "WARNING" not in res.output  # Prefect's own records stay off the console
    # the console's table says the run's own status, as REPORT.md does
    assert any("phantom001n" in line and "check" in line for line in res.output.splitlines())
    df = pd.read_parquet(tmp_path / "ev" / "evaluation.parquet").set_index("patient_id")
    assert list(df.index) == ["phantom000", "phantom001n"]
    assert set(df["status"]) == {"ok"} and set(df["reference_kind"]) == {"truth", "tumor_free"}
    # evaluated, and the tumour-free run asks to confirm its empty result (run_status)
    assert df.loc["phantom001n", "run_status"] == "check"
    assert df.loc["phantom001n", "notes"].startswith("no tumour found: confirm")
    # issue 28 item 5: when to check, as metrics.parquet publishes it
    assert df.loc["phantom001n", "needs_review"]
    assert df.loc["phantom001n", "review_reasons"].startswith("no tumour found: confirm")
    assert df.loc["phantom000", "needs_review"] == (df.loc["phantom000", "run_status"] == "check")
    report = (tmp_path / "ev" / "REPORT.md").read_text()
    assert "| phantom001n |" in report and "default: check" in report.split("## Table 2")[0]
    table2 = report.split("## Table 2")[1].split("## Table 3")[0]
    table3 = report.split("## Table 3")[1].split("\n## ")[0]
    for pid in ("phantom000", "phantom001n"):
        assert f"| {pid} |" in table2 and f"| {pid} |" in table3


def test_the_geometry_evaluations_run_when_named(evaluated, tmp_path):
    """--evaluation interpolation/simplification: their columns and report sections
    (issue 30); the cohort itself comes from the cache of the first evaluation."""
    from tumor3d.flows.evaluate import run_evaluation

    result, out = evaluated
    manifest = next((out.parent / "in").glob("*.csv"))
    again = run_evaluation(  # one manifest's path as a str (was read letter by letter)
        str(manifest), tmp_path / "geo", store_dir=out / ".tumor3d-store", command="pytest",
        evaluations=["interpolation", "simplification"],
    )  # fmt: skip
    df = pd.read_parquet(tmp_path / "geo" / "evaluation.parquet")
    ok = df[df["status"] == "ok"]
    assert len(ok) == 2
    assert ok["interp_se_eps_percent"].notna().all()
    assert ok["simp_curvature_p60_eq11_mm"].notna().all()
    assert "dice_3d" not in df.columns  # segmentation was not asked for
    report = again.report.read_text()
    assert "### interpolation (default)" in report and "### simplification (default)" in report
    # and no segmentation tables left empty: they belong to the segmentation evaluation
    assert "## Table 2" not in report and "## Volumes" not in report
    assert "## Table 2" in (out / "REPORT.md").read_text()
    assert not list((tmp_path / "geo").glob("bland_altman_*.png"))
