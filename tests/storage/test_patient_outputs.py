"""Tests of tumor3d.storage.patient_outputs and the cohort page rows: links only to what exists."""

from __future__ import annotations

import pandas as pd

from tumor3d.storage.cohort_report import cohort_page_rows, write_cohort_outputs
from tumor3d.storage.patient_outputs import join_notes, patient_report_data, split_notes
from tumor3d.storage.report_html import patient_report_html

METRICS = {
    "patient_id": "p1", "volume_eq7_mm3": 21774.9, "volume_eq7_ml": 21.7749,
    "volume_voxel_mm3": 21060.4, "volume_mesh_mm3": 21022.4,
    "volume_mesh_simplified_mm3": 21022.4, "volume_eq7_ce": 0.02,
    "volume_eq7_ci95_low_mm3": 20921.3, "volume_eq7_ci95_high_mm3": 22628.5,
    "rano_longest_mm": 41.25, "rano_perpendicular_mm": 30.0, "rano_product_mm2": 1237.5,
    "rano_slice_index": 12, "max_diameter_3d_mm": 44.0, "n_slices": 31,
    "n_tumor_slices": 9, "n_eq7_slices": 9, "eq7_slice_rule": "segmented",
    "faces_mc": 12000, "faces_simplified": 4800, "slab_height_mm": 5.0,
    "tumour_found": True, "notes": "",
}  # fmt: skip
RUNS = [
    {"stage": "segment-tumor", "compute_seconds": 0.5, "cached": True},
    {"stage": "render-views", "compute_seconds": 1.5, "cached": False},
]


def test_report_links_only_the_files_that_were_written():
    files = ["render_anterior.png", "render_cut_axial.png", "overlay_tumor.png", "metrics.parquet"]
    data = patient_report_data(METRICS, stage_runs=RUNS, abnormal_slices=[10, 11], files=files)
    assert data["renders"] == {
        "anterior": "render_anterior.png",
        "cut_axial": "render_cut_axial.png",
    }
    assert list(data["overlays"].values()) == ["overlay_tumor.png"]
    assert "viewer" not in data and "turntable" not in data
    assert data["eq7_precision"] == {"ce": 0.02, "ci95_low_mm3": 20921.3, "ci95_high_mm3": 22628.5}
    longest = data["measurements"]["RANO-style longest in-plane diameter"]
    assert longest == "41.2 mm"  # 41.25 rounds even
    assert data["stage_cached"] == {"segment-tumor": True, "render-views": False}
    page = patient_report_html(data)
    assert "21,774.9" in page and "21.775" in page and "20,921.3 to 22,628.5" in page


def test_tumour_free_report_has_no_interval_and_says_so():
    metrics = {**METRICS, "tumour_found": False, "volume_eq7_mm3": 0.0, "volume_eq7_ce": 0.0,
               "volume_eq7_ci95_low_mm3": 0.0, "volume_eq7_ci95_high_mm3": 0.0,
               "notes": "no tumour found: no mesh and no render written"}  # fmt: skip
    data = patient_report_data(metrics, stage_runs=RUNS, abnormal_slices=[], files=[])
    # no tumour is a finding, not a doubt: status ok, and the note says it
    assert data["status"] == "ok" and "eq7_precision" not in data
    assert data["notes"] == ["no tumour found: no mesh and no render written"]
    assert data["measurements"] == {} and data["renders"] == {}
    assert "no mesh and no render written" in patient_report_html(data)


def test_each_note_reaches_the_report_whole_even_with_the_separator_inside_it():
    # a given brain mask's file name (or any sentence) may hold "; ", the separator of the
    # notes in metrics.parquet: the note must come back as one, not as two
    notes = ["brain mask given (a; b.nii.gz, sha256 0123)", "no tumour found: no mesh"]
    joined = join_notes(notes)
    assert split_notes(joined) == ["brain mask given (a, b.nii.gz, sha256 0123)", notes[1]]
    data = patient_report_data({**METRICS, "notes": joined}, stage_runs=RUNS,
                               abnormal_slices=[], files=[])  # fmt: skip
    assert len(data["notes"]) == 2 and data["notes"][1] == notes[1]
    assert split_notes(None) == [] and split_notes(float("nan")) == [] and join_notes([]) == ""


def test_brain_volume_note_is_one_note():
    from tumor3d.imaging.preprocess import brain_volume_note

    note = brain_volume_note(3257.0)
    assert note is not None and split_notes(join_notes([note])) == [note]


def test_cohort_rows_link_existing_files_of_published_patients_only(tmp_path):
    for pid in ("a", "b"):
        (tmp_path / pid).mkdir()
        (tmp_path / pid / "report.html").write_text("<html></html>")
    (tmp_path / "a" / "render_anterior.png").write_bytes(b"png")
    table = pd.DataFrame(
        [
            {"patient_id": "a", "status": "ok", "failed_stage": None, "error": None,
             "volume_eq7_mm3": 1500.0, "tumour_found": True},
            {"patient_id": "b", "status": "failed", "failed_stage": "segment-tumor",
             "error": "RuntimeError: boom", "volume_eq7_mm3": float("nan"), "tumour_found": None},
            {"patient_id": "c", "status": "ok", "failed_stage": None, "error": None,
             "volume_eq7_mm3": 0.0, "tumour_found": False,
             "notes": "no tumour found: no mesh and no render written"},
            {"patient_id": "d", "status": "check", "failed_stage": None, "error": None,
             "volume_eq7_mm3": 80800.0, "tumour_found": True,
             "review_reasons": "the brain mask (2,886 mL) makes the result unreliable",
             "notes": "brain mask given (m.nii.gz); "
                      "the brain mask (2,886 mL) makes the result unreliable"},
        ]
    )  # fmt: skip
    rows = cohort_page_rows(table, tmp_path)
    assert rows[0] == {"patient_id": "a", "status": "ok", "volumes_mm3": {"eq7": 1500.0},
                       "notes": [], "thumbnail": "a/render_anterior.png",
                       "report": "a/report.html"}  # fmt: skip
    # b failed this time: its folder (an earlier run's) is not linked
    assert rows[1] == {"patient_id": "b", "status": "failed at segment-tumor: RuntimeError: boom"}
    assert rows[2]["status"] == "ok" and "report" not in rows[2]
    assert rows[2]["notes"] == ["no tumour found: no mesh and no render written"]
    # a result the tool doubts: check, the reason first and not repeated
    assert rows[3]["status"] == "check" and rows[3]["volumes_mm3"] == {"eq7": 80800.0}
    assert rows[3]["notes"] == ["the brain mask (2,886 mL) makes the result unreliable",
                                "brain mask given (m.nii.gz)"]  # fmt: skip
    write_cohort_outputs(tmp_path, table, "# md\n")
    page = (tmp_path / "cohort.html").read_text()
    assert 'href="a/report.html"' in page and 'href="b/report.html"' not in page
    assert '<td class="status-check">check</td>' in page and "<th>Notes</th>" in page
    assert "makes the result unreliable" in page and "no tumour found" in page
    # the folder's name is not repeated after "cohort" (was "tumor3d cohort <name>")
    assert "<title>tumor3d cohort: " + tmp_path.name + "</title>" in page
    assert (tmp_path / "cohort.parquet").is_file() and (tmp_path / "cohort.md").is_file()


def test_the_report_says_what_is_measured_and_on_which_sequence_the_diameters_are():
    from tumor3d.segmentation.segment import lesion_definition
    from tumor3d.storage.report_html import patient_report_markdown, patient_summary_table

    words = lesion_definition("robust", "flair")
    metrics = {**METRICS, "modality": "flair", "segment_method": "robust", "measured": words}
    data = patient_report_data(metrics, stage_runs=RUNS, abnormal_slices=[10], files=[])
    assert data["measured"] == words and "oedema" in words
    assert f"What is measured: {words}" in patient_report_html(data)
    assert f"What is measured: {words}" in patient_report_markdown(data)
    assert {"quantity": "what is measured", "value": words, "unit": ""} in patient_summary_table(
        data
    )
    assert "FLAIR whole tumour, oedema included" in data["measurements"]["RANO-style diameters of"]
    t1c = patient_report_data({**metrics, "modality": "t1c"}, stage_runs=RUNS,
                              abnormal_slices=[10], files=[])  # fmt: skip
    assert "RANO-style diameters of" not in t1c["measurements"]  # RANO's own sequence


def test_the_report_names_the_method_that_ran_and_how_the_input_was_read():
    """A user audit found the method only in the folded provenance JSON, and the input's
    orientation nowhere: the page, its table and the markdown say both."""
    from tumor3d.storage.report_html import patient_report_markdown, patient_summary_table

    metrics = {**METRICS, "segment_method": "learned", "segment_model": "forest + U-Net mean"}
    provenance = {"input": {"orientation": {"stored": "LAS", "read_as": "LPS"}}}
    data = patient_report_data(
        metrics, stage_runs=RUNS, abnormal_slices=[10], files=[], provenance=provenance
    )
    said = (
        "Segmentation method learned (forest + U-Net mean); input orientation stored LAS, "
        "read as LPS."
    )
    assert said in patient_report_html(data)
    rows = patient_summary_table(data)
    assert {"quantity": "segmentation method", "value": "learned (forest + U-Net mean)",
            "unit": ""} in rows  # fmt: skip
    assert {"quantity": "input orientation", "value": "stored LAS, read as LPS", "unit": ""} in rows
    assert "stored LAS, read as LPS" in patient_report_markdown(data)
    # a file in the working orientation, and a run recorded before either was
    lps = {"input": {"orientation": {"stored": "LPS", "read_as": "LPS"}}}
    data = patient_report_data(metrics, stage_runs=RUNS, abnormal_slices=[], files=[],
                               provenance=lps)  # fmt: skip
    assert data["orientation"] == "LPS, read as stored"
    old = patient_report_data(METRICS, stage_runs=RUNS, abnormal_slices=[], files=[])
    assert "orientation" not in old and old["method"] == ""
    assert "Segmentation method" not in patient_report_html(old)
