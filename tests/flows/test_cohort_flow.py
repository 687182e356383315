"""The cohort flow: N patients at a time, failure isolation, cohort outputs, caching.

Three phantoms and one row whose image is missing: three published patients,
one failed row, exit code 1; a second run is all cache hits; adding a fourth
patient computes only it.
"""

from __future__ import annotations

import dataclasses
import json
import time

import pandas as pd
import pytest
from typer.testing import CliRunner

from tumor3d.errors import InputError
from tumor3d.flows.cli import app
from tumor3d.flows.cohort import run_cohort
from tumor3d.phantom import make_phantom_patient
from tumor3d.storage.manifest import ManifestRow, write_manifest
from tumor3d.storage.phantom_io import write_phantom_patient
from tumor3d.tasks.stages import STAGES

# Small phantoms (128 x 128 pixels of 1.875 mm, the default field of view, 16 slices):
# what these tests check does not depend on the image size, and a run costs a third.
SMALL = {"n_slices": 16, "matrix_size": (128, 128)}

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_harness")]


def _phantom_row(seed: int, folder) -> ManifestRow:
    patient = make_phantom_patient(seed, patient_id=f"coh{seed}", **SMALL)
    return write_phantom_patient(patient, folder / f"coh{seed}")


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    folder = tmp_path_factory.mktemp("cohort-in")
    rows = [_phantom_row(s, folder) for s in (0, 1, 2)]
    missing = ManifestRow(patient_id="ghost", image=folder / "ghost_t2.nii.gz", modality="t2")
    return folder, rows, missing


@pytest.fixture(scope="module")
def first(inputs, tmp_path_factory):
    _, rows, missing = inputs
    out = tmp_path_factory.mktemp("cohort-out")
    return out, run_cohort([rows[0], missing, *rows[1:]], out, workers=2)


def test_failed_row_is_isolated_and_the_others_publish(first):
    out, result = first
    assert result.exit_code == 1
    by_id = {p.patient_id: p for p in result.patients}
    assert [p.patient_id for p in result.patients] == ["coh0", "ghost", "coh1", "coh2"]
    ghost = by_id["ghost"]
    assert ghost.status == "failed" and ghost.failed_stage == "prepare-input"
    assert "no such file" in ghost.error and "\n" not in ghost.error
    assert ghost.output_dir is None and not (out / "ghost").exists()
    for pid in ("coh0", "coh1", "coh2"):
        p = by_id[pid]
        assert p.status == "ok" and p.error is None
        assert p.output_dir == str(out / pid)
        published = pd.read_parquet(out / pid / "metrics.parquet").iloc[0]
        # a clean phantom: nothing asks for a human
        assert published["status"] == "ok" and not published["needs_review"]
        assert published["review_reasons"] == ""
        assert published["volume_eq7_mm3"] == p.metrics["volume_eq7_mm3"] > 0
        assert not any(s.cached for s in p.stages)
    assert not [q for q in out.iterdir() if ".partial-" in q.name or ".old-" in q.name]


def test_each_lane_times_its_patient_stages_and_publishing(first):
    """What the cohort benchmark splits a lane's time into: stages, publishing, the rest."""
    _, result = first
    for p in result.patients:
        stage_wall = sum(s.wall_seconds for s in p.stages)
        assert p.lane_seconds <= result.wall_seconds
        if p.status == "failed":  # ghost: no stage, nothing published
            assert p.publish_seconds == 0.0 and p.stages == [] and 0 < p.lane_seconds
        else:
            assert 0 < p.publish_seconds and stage_wall > 0
            assert stage_wall + p.publish_seconds < p.lane_seconds


def test_cohort_table_and_report(first):
    out, result = first
    table = pd.read_parquet(out / "cohort.parquet")
    assert list(table["patient_id"]) == ["coh0", "ghost", "coh1", "coh2"]
    assert list(table["status"]) == ["ok", "failed", "ok", "ok"]
    # relative to the cohort's folder, wherever the command ran (was: to its working folder)
    assert [None if pd.isna(v) else v for v in table["output_dir"]] == [
        "coh0", None, "coh1", "coh2"
    ]  # fmt: skip
    metrics_cols = set(pd.read_parquet(out / "coh1" / "metrics.parquet").columns)
    assert metrics_cols <= set(table.columns)
    ok = table.set_index("patient_id").loc["coh1"]
    assert ok["volume_mesh_mm3"] == result.patients[2].metrics["volume_mesh_mm3"]
    assert pd.isna(table.set_index("patient_id").loc["ghost"]["volume_eq7_mm3"])
    md = (out / "cohort.md").read_text()
    assert "ghost" in md and "prepare-input" in md and "mL" in md
    # each row says its sequence (T1c's core and FLAIR's whole tumour are other things) and
    # the slices Eq. 7 summed with their rule
    row = next(line for line in md.splitlines() if line.startswith("| coh1 |"))
    assert row.startswith(f"| coh1 | ok | {ok['modality']} | ")
    assert f"| {int(ok['n_eq7_slices'])} (segmented) |" in row
    for stage in STAGES:
        assert f"| {stage} |" in md


def test_cohort_page_links_every_published_patient_and_loads(first, tmp_path):
    import shutil

    from headless_chromium import CHROMIUM, local_links, open_page, unresolved_links

    out, _ = first
    page = out / "cohort.html"
    assert page.is_file()
    targets = local_links(page)
    for pid in ("coh0", "coh1", "coh2"):
        assert f"{pid}/report.html" in targets and f"{pid}/render_anterior.png" in targets
    assert not [t for t in targets if t.startswith("ghost")]  # a failed row links nothing
    text = page.read_text()
    assert "failed at prepare-input" in text and text.count("<circle") == 3
    moved = tmp_path / "moved"
    shutil.copytree(out, moved, ignore=shutil.ignore_patterns(".tumor3d-store"))
    assert unresolved_links(moved / "cohort.html") == []
    if CHROMIUM is not None:
        shown = open_page(moved / "cohort.html", tmp_path, budget_ms=3000)
        assert shown.js_errors == []
        assert len(shown.images) == 3 and all(w > 0 for _, w in shown.images)


def test_cohort_table_artifact_is_on_the_cohort_flow_run(first):
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterKey

    from tumor3d.flows.artifacts import artifact_key

    out, _ = first
    key = artifact_key("tumor3d", "cohort", out.name)
    with get_client(sync_client=True) as client:
        arts = client.read_artifacts(
            artifact_filter=ArtifactFilter(key=ArtifactFilterKey(any_=[key]))
        )
        assert arts, key
        run = client.read_flow_run(arts[0].flow_run_id)
        assert run.name.startswith(f"cohort-{out.name}")
    # a patient failed: the run is Failed in Prefect, as a scheduled run is (it showed
    # Completed, so monitoring that reads Prefect missed it); run_cohort still returned
    assert run.state is not None and run.state.is_failed(), run.state
    assert run.state.message == "1 of 4 patients failed: ghost"
    rows = arts[0].data
    rows = json.loads(rows) if isinstance(rows, str) else rows
    assert [r["patient_id"] for r in rows] == ["coh0", "ghost", "coh1", "coh2"]
    assert [r["status"] for r in rows] == ["ok", "failed", "ok", "ok"]


def test_a_direct_call_of_the_failed_cohort_flow_raises_with_its_result(inputs, tmp_path):
    """``cohort_flow`` called as a flow (a custom task runner: docs/ARCHITECTURE.md) raises
    ``PatientsFailed`` holding the whole result when some patient failed, as Prefect raises
    a failed flow's error (a Failed state holding the plain result made Prefect raise a
    TypeError instead: the review of bc8ef5d)."""
    from tumor3d.flows.cohort import cohort_flow
    from tumor3d.flows.cohort_result import PatientsFailed

    _, _, missing = inputs
    row = {"patient_id": "ghost", "image": str(missing.image), "modality": "t2"}
    with pytest.raises(PatientsFailed, match="1 of 1 patient failed: ghost") as exc:
        cohort_flow(rows=[row], out_dir=str(tmp_path / "out"))
    assert [p.status for p in exc.value.result.patients] == ["failed"]


def test_the_flow_run_is_tagged_and_its_stage_task_runs_are_not(first):
    """The ``config:``/``cohort`` tags (and the process's) stay on the flow run: a tagged
    task run costs a round trip to the server for tag concurrency slots, every stage of
    every patient."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import (
        ArtifactFilter,
        ArtifactFilterKey,
        FlowRunFilter,
        FlowRunFilterId,
    )

    from tumor3d.config import parse_config
    from tumor3d.flows.artifacts import artifact_key
    from tumor3d.flows.patient import config_digest
    from tumor3d.flows.stale_runs import process_tags

    out, _ = first
    key = artifact_key("tumor3d", "cohort", out.name)
    with get_client(sync_client=True) as client:
        (art,) = client.read_artifacts(
            artifact_filter=ArtifactFilter(key=ArtifactFilterKey(any_=[key]))
        )
        run = client.read_flow_run(art.flow_run_id)
        # the server records task runs from their events, in batches (tests/conftest.py)
        deadline = time.monotonic() + 60
        while True:
            task_runs = client.read_task_runs(
                flow_run_filter=FlowRunFilter(id=FlowRunFilterId(any_=[run.id])), limit=200
            )
            if len(task_runs) >= 3 * len(STAGES) or time.monotonic() > deadline:
                break
            time.sleep(0.2)
    # ... with this process's tags (tumor3d.flows.stale_runs), as a command's runs
    assert set(run.tags) == {
        "cohort",
        f"config:{config_digest(parse_config({}))[:12]}",
        *process_tags(),
    }
    assert len(task_runs) == 3 * len(STAGES)  # three patients published, ghost ran none
    assert [t.tags for t in task_runs if t.tags] == []


def test_rerun_is_all_cache_hits_and_a_new_patient_computes_alone(first, inputs):
    """...and the re-run sweeps the temporary object file of a writer killed before it."""
    import os
    import subprocess
    import sys

    from tumor3d.storage.store import HOST_TAG

    out, result = first
    folder, rows, _ = inputs
    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    objects = out / ".tumor3d-store" / "objects"
    some = next(p for p in objects.glob("*/*") if not p.name.startswith("."))
    killed = some.with_name(f".{some.name}.tmp-{HOST_TAG}-{gone.pid}-0123abcd")
    live = some.with_name(f".{some.name}.tmp-{HOST_TAG}-{os.getpid()}-0123abcd")
    killed.write_bytes(b"half")
    live.write_bytes(b"being written")
    from tumor3d.tasks.progress import use_reporter

    events = []
    with use_reporter(events.append):
        again = run_cohort(rows, out, workers=2)
    assert again.exit_code == 0
    assert not killed.exists() and live.exists()
    # the patients' last progress lines say nothing was rewritten (they said "published")
    done = {e.patient_id: e.stage for e in events if e.status == "published"}
    assert done == {p.patient_id: "up to date" for p in again.patients}
    live.unlink()
    for p in again.patients:
        missed = [(s.stage, s.repaired) for s in p.stages if not s.cached]
        assert not missed, (p.patient_id, missed)
        assert (
            p.metrics["volume_eq7_mm3"]
            == next(q for q in result.patients if q.patient_id == p.patient_id).metrics[
                "volume_eq7_mm3"
            ]
        )
    events.clear()
    with use_reporter(events.append):
        more = run_cohort([*rows, _phantom_row(3, folder)], out, workers=2)
    done = {e.patient_id: e.stage for e in events if e.status == "published"}
    assert done["coh3"] == "published" and set(done.values()) == {"published", "up to date"}
    hits = {p.patient_id: [s.cached for s in p.stages] for p in more.patients}
    assert not any(hits["coh3"])
    assert all(all(h) for pid, h in hits.items() if pid != "coh3")


def test_a_patient_computed_again_says_why(first, inputs, tmp_path):
    """A user audit re-ran a cohort and saw "cached 0/10" for every patient, with no way
    to tell that a code change caused it. A published patient whose stages ran again says
    why: here the render colour changed (only the render stage ran), and a cleared store;
    one all from the cache, or new, says nothing."""
    import io
    import shutil

    from rich.console import Console

    import tumor3d.flows.cli.output as output

    out, result = first
    _, rows, _ = inputs
    assert all(p.recomputed is None for p in result.patients)  # nothing published before
    copy = tmp_path / "out"
    shutil.copytree(out, copy)
    red_config = {"render": {"color_rgb": [0.9, 0.1, 0.1]}}
    red = run_cohort(rows[:2], copy, workers=2, config=red_config)
    for p in red.patients:
        assert [s.stage for s in p.stages if not s.cached] == ["render-views"], p.patient_id
        assert p.recomputed == "configuration changed", p.patient_id
    assert (
        pd.read_parquet(copy / "cohort.parquet")["recomputed"].tolist()
        == ["configuration changed"] * 2
    )
    assert "- configuration changed: coh0, coh1" in (copy / "cohort.md").read_text()
    shutil.rmtree(copy / ".tumor3d-store")
    cleared = run_cohort(rows[:1], copy, workers=1, config=red_config)
    assert cleared.patients[0].recomputed.startswith("nothing recorded changed, but the results")
    again = run_cohort(rows[:1], copy, workers=1, config=red_config)
    assert again.patients[0].recomputed is None  # all from the cache
    buf = io.StringIO()
    output.console, saved = Console(file=buf, width=200), output.console
    try:
        output.print_cohort_summary(red)
    finally:
        output.console = saved
    assert "since the earlier result, configuration changed: coh0, coh1" in buf.getvalue()
    assert pd.read_parquet(copy / "cohort.parquet")["recomputed"].isna().all()  # the last run's
    assert "Since the earlier result" not in (copy / "cohort.md").read_text()


def test_a_new_input_that_fails_says_its_folder_holds_the_earlier_result(first, inputs, tmp_path):
    """A patient published by an earlier run whose new image fails keeps the earlier folder
    (published results are not deleted): the run says that folder is not this input's, in
    its result, cohort.md, cohort.html's row (a user audit: the page a clinician opens
    said nothing) and the console line, and names no other patient."""
    import shutil

    out = tmp_path / "out"
    shutil.copytree(first[0], out)
    _, rows, _ = inputs
    broken = tmp_path / "coh0_t2.nii.gz"
    broken.write_bytes(rows[0].image.read_bytes()[:3000])  # cut short: ingest fails
    again = run_cohort([dataclasses.replace(rows[0], image=broken), rows[1]], out, workers=1)
    assert [p.status for p in again.patients] == ["failed", "ok"]
    assert again.earlier == ["coh0"]
    assert (out / "coh0" / "metrics.parquet").is_file()  # kept, not deleted
    md = (out / "cohort.md").read_text()
    assert "The folder of coh0 still holds an earlier run's result" in md
    rows = [r.split("</tr>")[0] for r in (out / "cohort.html").read_text().split("<tr>")]
    (coh0,) = [r for r in rows if ">coh0<" in r]
    (coh1,) = [r for r in rows if ">coh1<" in r]
    assert "its folder still holds an earlier run&#x27;s result" in coh0
    assert "earlier run" not in coh1
    from tumor3d.flows.cli.app import console
    from tumor3d.flows.cli.output import print_cohort_summary

    with console.capture() as captured:
        print_cohort_summary(again)
    assert "earlier result kept" in captured.get() and "coh0" in captured.get()


def test_cli_cohort_exit_codes(first, inputs, tmp_path):
    out, _ = first
    _, rows, _ = inputs
    manifest = write_manifest(rows, tmp_path / "manifest.csv")
    runner = CliRunner()
    ok = runner.invoke(app, ["cohort", str(manifest), "--out", str(out), "--workers", "2"])
    assert ok.exit_code == 0, ok.output
    assert "3 ok, 0 to check, 0 failed" in ok.output
    bad = runner.invoke(app, ["cohort", str(tmp_path / "absent.csv"), "--out", str(out)])
    assert bad.exit_code == 2
    bad_cfg = tmp_path / "bad.yaml"
    bad_cfg.write_text("simplify: {reduction_percent: 250}\n")
    res = runner.invoke(app, ["cohort", str(manifest), "--out", str(out), "--config", str(bad_cfg)])
    assert res.exit_code == 2 and "reduction_percent" in res.output


def test_cohort_refuses_an_output_folder_holding_an_input(inputs, tmp_path):
    folder, rows, _ = inputs
    # DIR/<id> would be the folder holding coh0's image: refused before any work
    with pytest.raises(Exception, match="would delete the input"):
        run_cohort([rows[0]], folder, workers=1)
    assert rows[0].image.exists()


def test_cli_cohort_missing_image_in_the_csv_fails_that_row_only(first, inputs, tmp_path):
    """Issue 12: a missing image in a manifest CSV exited 2 before any patient ran."""
    out, _ = first
    _, rows, missing = inputs
    lines = ["patient_id,image,modality"]
    lines += [f"{r.patient_id},{r.image},t2" for r in rows[:2]]
    lines.append(f"{missing.patient_id},{missing.image},t2")
    manifest = tmp_path / "with_ghost.csv"
    manifest.write_text("\n".join(lines) + "\n")
    res = CliRunner().invoke(app, ["cohort", str(manifest), "--out", str(out), "--workers", "2"])
    assert res.exit_code == 1, res.output
    assert "2 ok, 0 to check, 1 failed" in res.output and "ghost" in res.output
    table = pd.read_parquet(out / "cohort.parquet").set_index("patient_id")
    assert table.loc["ghost", "status"] == "failed"
    assert table.loc["ghost", "failed_stage"] == "prepare-input"
    assert "no such file" in table.loc["ghost", "error"]
    assert list(table.loc[["coh0", "coh1"], "status"]) == ["ok", "ok"]


def test_cli_cohort_max_voxels_fails_each_too_large_row(first, inputs, tmp_path):
    """--max-voxels reaches the reader of every row, even when the scan is cached."""
    out, _ = first
    _, rows, _ = inputs
    manifest = write_manifest(rows[:2], tmp_path / "two.csv")
    res = CliRunner().invoke(
        app, ["cohort", str(manifest), "--out", str(out), "--workers", "2", "--max-voxels", "1000"]
    )
    assert res.exit_code == 1, res.output
    table = pd.read_parquet(out / "cohort.parquet").set_index("patient_id")
    assert list(table["status"]) == ["failed", "failed"]
    assert set(table["failed_stage"]) == {"ingest-scan"}
    assert all("more than the limit of 1,000" in e for e in table["error"])
    # the cohort outputs of the first run are still published
    assert (out / "coh0" / "metrics.parquet").is_file()


def test_cli_cohort_brain_mask_column_and_a_bad_mask_fails_that_row_only(
    first, inputs, tmp_path, monkeypatch
):
    """Issue 7: the manifest's brain_mask (relative or ${VAR} path); a bad one fails alone."""
    import nibabel as nib
    import numpy as np

    out, _ = first
    _, rows, _ = inputs
    affine = nib.load(rows[2].image).affine
    labels = make_phantom_patient(2, patient_id="coh2", **SMALL).tissue_labels
    brain = np.isin(labels, (3, 4, 5, 6)).transpose(2, 1, 0).astype(np.uint8)  # NIfTI order
    nib.save(nib.Nifti1Image(brain, affine), tmp_path / "coh2_brain.nii.gz")
    nib.save(nib.Nifti1Image(brain[:, :, :-1], affine), tmp_path / "short.nii.gz")
    monkeypatch.setenv("MASKS", str(tmp_path))
    manifest = tmp_path / "masks.csv"
    manifest.write_text(
        "patient_id,image,modality,brain_mask\n"
        f"coh0,{rows[0].image},t2,\n"
        f"coh1,{rows[1].image},t2,short.nii.gz\n"
        f"coh2,{rows[2].image},t2,${{MASKS}}/coh2_brain.nii.gz\n"
    )
    res = CliRunner().invoke(app, ["cohort", str(manifest), "--out", str(out), "--workers", "2"])
    assert res.exit_code == 1, res.output
    assert "2 ok, 0 to check, 1 failed" in res.output
    table = pd.read_parquet(out / "cohort.parquet").set_index("patient_id")
    assert list(table["status"]) == ["ok", "failed", "ok"]
    assert table.loc["coh1", "failed_stage"] == "prepare-input"
    error = table.loc["coh1", "error"]
    assert f"{tmp_path / 'short.nii.gz'}: brain mask: shape" in error and "\n" not in error
    given = json.loads((out / "coh2" / "provenance.json").read_text())["brain_mask"]
    assert given["given"] is True and given["file"] == "coh2_brain.nii.gz"
    assert json.loads((out / "coh0" / "provenance.json").read_text())["brain_mask"] == {
        "given": False, "rule": "found from the image (preprocess brain_extraction)",
        "extraction": "skull_strip",  # a raw phantom head: the auto rule's skull removal
    }  # fmt: skip


def test_status_ok_check_failed_through_metrics_table_pages_console_and_exit_code(
    first, inputs, tmp_path
):
    """Issue 33: a result the tool's own checks doubt is "check", never a green "ok"."""
    import nibabel as nib
    import numpy as np

    out, _ = first
    _, rows, missing = inputs
    img = nib.load(rows[1].image)
    # a "brain" mask over the whole field of view: more than any skull holds, so the
    # run's own note says the result is unreliable
    nib.save(nib.Nifti1Image(np.ones(img.shape, np.uint8), img.affine), tmp_path / "all.nii.gz")
    manifest = tmp_path / "status.csv"
    manifest.write_text(
        "patient_id,image,modality,brain_mask\n"
        f"coh0,{rows[0].image},t2,\n"
        f"coh1,{rows[1].image},t2,{tmp_path / 'all.nii.gz'}\n"
        f"ghost,{missing.image},t2,\n"
    )
    dest = tmp_path / "out"
    store = str(out / ".tumor3d-store")  # coh0 from the cache
    runner = CliRunner()
    res = runner.invoke(app, ["cohort", str(manifest), "--out", str(dest), "--store", store])
    assert res.exit_code == 1, res.output  # a failure outranks a check
    assert "1 ok, 1 to check, 1 failed" in res.output
    assert "check coh1: brain mask of" in " ".join(res.output.split())
    table = pd.read_parquet(dest / "cohort.parquet").set_index("patient_id")
    assert list(table["status"]) == ["ok", "check", "failed"]
    assert table.loc["coh1", "needs_review"] and not table.loc["coh0", "needs_review"]
    assert "more than any skull holds" in table.loc["coh1", "review_reasons"]
    metrics = pd.read_parquet(dest / "coh1" / "metrics.parquet").iloc[0]
    assert metrics["status"] == "check" and metrics["needs_review"]
    reasons = metrics["review_reasons"].split("; ")
    assert set(reasons) < set(metrics["notes"].split("; "))  # + "brain mask given (...)"
    md = (dest / "cohort.md").read_text()
    assert "1 ok, 1 to check, 1 failed" in md and "| coh1 | **check** |" in md
    assert "more than any skull holds" in md and "| coh0 | ok |" in md
    page = (dest / "cohort.html").read_text()
    assert '<td class="status-check">check</td>' in page and "<th>Notes</th>" in page
    assert "<title>tumor3d cohort: out</title>" in page
    report = (dest / "coh1" / "report.html").read_text()
    assert '<strong class="status-check">check</strong>' in report
    # no failure: the check alone decides the exit code (4), for a cohort and for `run`
    no_ghost = tmp_path / "no_ghost.csv"
    no_ghost.write_text("\n".join(manifest.read_text().splitlines()[:3]) + "\n")
    res = runner.invoke(app, ["cohort", str(no_ghost), "--out", str(dest), "--store", store])
    assert res.exit_code == 4, res.output
    one = runner.invoke(app, [
        "run", str(rows[1].image), "--out", str(tmp_path / "one"), "--patient-id", "coh1",
        "--brain-mask", str(tmp_path / "all.nii.gz"), "--store", store,
    ])  # fmt: skip
    assert one.exit_code == 4, one.output
    assert "status: check" in one.output and "more than any skull holds" in one.output
    clean = runner.invoke(app, [
        "run", str(rows[0].image), "--out", str(tmp_path / "one"), "--patient-id", "coh0",
        "--store", store, "--modality", "t2",
    ])  # fmt: skip
    assert clean.exit_code == 0, clean.output
    assert "status: ok" in clean.output
    # the same without --modality: T2 assumed, said, and a check (a user audit: a FLAIR
    # run so was segmented as T2, twice its tumour's volume, with status ok)
    assumed = runner.invoke(app, [
        "run", str(rows[0].image), "--out", str(tmp_path / "one"), "--patient-id", "coh0",
        "--store", store,
    ])  # fmt: skip
    assert assumed.exit_code == 4, assumed.output
    assert "status: check" in " ".join(assumed.output.split())
    assert "modality: t2 by default" in " ".join(assumed.output.split())


def _seg_manifest(path, lines):
    path.write_text("patient_id,image,modality,segmentation\n" + "\n".join(lines) + "\n")
    return path


def test_cli_cohort_segmentation_column_replaces_that_rows_segmentation(first, inputs, tmp_path):
    """Issue 33: the manifest's segmentation (a relative path); the other row segments as usual."""
    import hashlib
    import shutil

    import nibabel as nib
    import numpy as np

    out, result = first
    folder, rows, _ = inputs
    (tmp_path / "masks").mkdir()
    mask = tmp_path / "masks" / "coh0_seg.nii.gz"  # the phantom's own true slice mask
    shutil.copyfile(folder / "coh0" / "coh0_truth_slices.nii.gz", mask)
    sha = hashlib.sha256(mask.read_bytes()).hexdigest()
    manifest = _seg_manifest(
        tmp_path / "seg.csv",
        [f"coh0,{rows[0].image},t2,masks/coh0_seg.nii.gz", f"coh1,{rows[1].image},t2,"],
    )
    dest = tmp_path / "out"
    store = str(out / ".tumor3d-store")
    res = CliRunner().invoke(app, ["cohort", str(manifest), "--out", str(dest), "--store", store])
    assert res.exit_code == 0, res.output
    assert "2 ok, 0 to check, 0 failed" in res.output
    # the truth, computed here: true tumour pixels x pixel area x slab height
    patient = make_phantom_patient(0, patient_id="coh0", **SMALL)
    truth = np.asarray(patient.slice_masks, bool)
    dy, dx = patient.scan.pixel_spacing_mm
    slab = patient.scan.slice_thickness_mm + patient.scan.slice_gap_mm
    expected = float(truth.sum()) * dy * dx * slab
    assert expected > 1000.0
    given = pd.read_parquet(dest / "coh0" / "metrics.parquet").iloc[0]
    assert given["volume_eq7_mm3"] == pytest.approx(expected, rel=1e-9)
    assert given["segment_method"] == "given"
    assert given["measured"] == "the segmentation given by the user (coh0_seg.nii.gz)"
    assert given["status"] == "ok"
    published = np.asarray(nib.load(dest / "coh0" / "tumor_mask_slices.nii.gz").dataobj)
    np.testing.assert_array_equal(published.transpose(2, 1, 0) > 0, truth)
    prov = json.loads((dest / "coh0" / "provenance.json").read_text())["segmentation"]
    assert prov["given"] is True and prov["file"] == "coh0_seg.nii.gz" and prov["sha256"] == sha
    assert hashlib.sha256(mask.read_bytes()).hexdigest() == sha  # only read
    # the row without one is segmented as usual: the first run's result, from the cache
    usual = pd.read_parquet(dest / "coh1" / "metrics.parquet").iloc[0]
    assert usual["segment_method"] != "given"
    before = next(p for p in result.patients if p.patient_id == "coh1")
    assert usual["volume_eq7_mm3"] == before.metrics["volume_eq7_mm3"]
    usual_prov = json.loads((dest / "coh1" / "provenance.json").read_text())
    assert usual_prov["segmentation"]["given"] is False
    table = pd.read_parquet(dest / "cohort.parquet").set_index("patient_id")
    assert "segmentation: given (coh0_seg.nii.gz" in table.loc["coh0", "notes"]


def test_cli_cohort_a_bad_segmentation_fails_that_row_only(first, inputs, tmp_path):
    import nibabel as nib
    import numpy as np

    out, _ = first
    _, rows, _ = inputs
    img = nib.load(rows[1].image)
    short = tmp_path / "short_seg.nii.gz"
    nib.save(nib.Nifti1Image(np.zeros(img.shape[:2] + (img.shape[2] - 1,), np.uint8),
                             img.affine), short)  # fmt: skip
    manifest = _seg_manifest(
        tmp_path / "bad.csv", [f"coh0,{rows[0].image},t2,", f"coh1,{rows[1].image},t2,{short}"]
    )
    dest = tmp_path / "out"
    store = str(out / ".tumor3d-store")
    res = CliRunner().invoke(app, ["cohort", str(manifest), "--out", str(dest), "--store", store])
    assert res.exit_code == 1, res.output
    assert "1 ok, 0 to check, 1 failed" in res.output
    table = pd.read_parquet(dest / "cohort.parquet").set_index("patient_id")
    assert list(table["status"]) == ["ok", "failed"]
    assert table.loc["coh1", "failed_stage"] == "prepare-input"
    error = table.loc["coh1", "error"]
    assert f"{short}: segmentation: shape" in error and "\n" not in error
    assert (dest / "coh0" / "metrics.parquet").is_file() and not (dest / "coh1").exists()


def test_cohort_refuses_a_segmentation_inside_another_rows_output(first, inputs, tmp_path):
    """Issue 29's cross-row rule holds for the segmentation column too (before any work)."""
    import shutil

    out, _ = first
    _, rows, _ = inputs
    dest = tmp_path / "out"
    shutil.copytree(out / "coh1", dest / "coh1")  # coh1's published result
    kept = dest / "coh1" / "my_seg.nii.gz"  # a user-edited copy kept in coh1's folder
    kept.write_bytes(b"mask")
    seg_row = dataclasses.replace(rows[0], segmentation=kept)
    with pytest.raises(InputError, match="my_seg.nii.gz"):
        run_cohort([seg_row, rows[1]], dest, workers=1)
    assert kept.read_bytes() == b"mask"
