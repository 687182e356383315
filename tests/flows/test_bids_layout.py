"""--layout bids: a phantom published as BIDS derivatives (issue 33, item 4).

The tree, the names (checked with a regex of BIDS 1.9's entity order written
here, independently of tumor3d.storage.bids: the bids-validator, a Deno/npm program,
is not installed), every NIfTI re-read by nibabel on the input's grid with
the default layout's voxel counts, the dataset description and sidecars, the
GIFTI surfaces against the PLY files, a re-run that is up to date, and the
refusals (a label that is not alphanumeric, another tool's dataset).
"""

from __future__ import annotations

import json
import re
import shutil

import nibabel as nib
import numpy as np
import pandas as pd
import pytest
from headless_chromium import unresolved_links
from typer.testing import CliRunner

import tumor3d
from tumor3d.errors import InputError
from tumor3d.flows.cli import app
from tumor3d.flows.patient import run_patient
from tumor3d.phantom import make_phantom_patient
from tumor3d.storage.formats import decode_ply
from tumor3d.storage.phantom_io import write_phantom_patient

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_harness")]

# BIDS 1.9 file names used here: sub, [hemi], [space], [label], [desc], then _suffix.ext
ENTITY_ORDER = re.compile(
    r"^sub-[A-Za-z0-9]+(_hemi-[LR])?(_space-[A-Za-z0-9]+)?(_label-[A-Za-z0-9]+)?"
    r"(_desc-[A-Za-z0-9]+)?_[A-Za-z0-9]+(\.nii\.gz|\.json|\.surf\.gii|\.ply|\.stl|\.vtk|"
    r"\.png|\.gif)$"
)

MASKS = {  # default-layout name -> BIDS name (after sub-<label>_), the BIDS 1.9 derivatives names
    "tumor_mask.nii.gz": "desc-tumor_mask.nii.gz",
    "tumor_mask_slices.nii.gz": "desc-tumorslices_mask.nii.gz",
    "brain_mask.nii.gz": "desc-brain_mask.nii.gz",
}


@pytest.fixture(scope="module")
def published(tmp_path_factory):
    base = tmp_path_factory.mktemp("bids")
    patient = make_phantom_patient(3, patient_id="bp1", n_slices=16)
    image = write_phantom_patient(patient, base / "in").image
    store = str(base / "store")
    default = run_patient(image, base / "default", patient_id="bp1", store_dir=store)
    first = run_patient(image, base / "bids", patient_id="bp1", store_dir=store, layout="bids")
    return image, base, default, first


def test_the_tree_has_bids_names_and_the_masks_are_on_the_input_grid(published):
    image, base, default, first = published
    sub = base / "bids" / "sub-bp1"
    assert first.output_dir == str(sub) and not first.up_to_date
    anat = sorted(p.name for p in (sub / "anat").iterdir())
    figures = sorted(p.name for p in (sub / "figures").iterdir())
    for name in anat + figures:
        assert ENTITY_ORDER.match(name), name
    for bids_name in MASKS.values():
        assert f"sub-bp1_{bids_name}" in anat
        assert f"sub-bp1_{bids_name.replace('.nii.gz', '.json')}" in anat
    for name in ("sub-bp1_tumor.surf.gii", "sub-bp1_tumor.ply", "sub-bp1_desc-lps_tumor.vtk",
                 "sub-bp1_desc-simplified_tumor.surf.gii", "sub-bp1_brain.surf.gii"):  # fmt: skip
        assert name in anat
    assert "sub-bp1_desc-anterior_render.png" in figures
    assert "sub-bp1_desc-tumor_overlay.png" in figures
    for name in ("report.html", "provenance.json", "metrics.parquet", "slices.parquet"):
        assert (sub / name).is_file()
    # nothing of the default layout's names left at the subject's top level
    assert not (sub / "tumor_mask.nii.gz").exists() and not (sub / "tumor.ply").exists()
    src = nib.load(image)
    for old, new in MASKS.items():
        mask = nib.load(sub / "anat" / f"sub-bp1_{new}")
        ref = nib.load(base / "default" / "bp1" / old)
        if old != "tumor_mask.nii.gz":  # the acquired slices' masks: the input's grid
            assert mask.shape == src.shape
            assert np.allclose(mask.affine, src.affine, atol=1e-5)
        else:  # the interpolated mask: slices added between the acquired ones
            assert mask.shape[:2] == src.shape[:2] and mask.shape[2] > src.shape[2]
        assert mask.shape == ref.shape and np.allclose(mask.affine, ref.affine, atol=1e-6)
        got, want = np.asarray(mask.dataobj), np.asarray(ref.dataobj)
        assert int((got > 0).sum()) == int((want > 0).sum()) > 0, old
    assert set(default.metrics) <= set(first.metrics)


def test_dataset_description_and_sidecars(published):
    _, base, _, first = published
    desc = json.loads((base / "bids" / "dataset_description.json").read_text())
    assert desc["DatasetType"] == "derivative"
    assert desc["BIDSVersion"].startswith("1.")
    assert {"Name", "BIDSVersion", "DatasetType", "GeneratedBy"} <= desc.keys()
    assert desc["GeneratedBy"][0]["Name"] == "tumor3d"
    assert desc["GeneratedBy"][0]["Version"] == tumor3d.__version__
    assert "*.ply" in (base / "bids" / ".bidsignore").read_text().split()
    anat = base / "bids" / "sub-bp1" / "anat"
    tumour = json.loads((anat / "sub-bp1_desc-tumor_mask.json").read_text())
    assert tumour["Type"] == "Lesion"
    assert tumour["Sources"] == ["bids::sub-bp1/anat/sub-bp1_desc-tumorslices_mask.nii.gz"]
    published_metrics = pd.read_parquet(base / "bids" / "sub-bp1" / "metrics.parquet").iloc[0]
    for method in ("eq7", "voxel", "mesh"):
        vol = tumour["Volumes"][method]
        assert vol["mm3"] == pytest.approx(published_metrics[f"volume_{method}_mm3"])
        assert vol["mL"] == pytest.approx(vol["mm3"] / 1000.0)
        assert len(vol["Method"]) > 10
    assert json.loads((anat / "sub-bp1_desc-brain_mask.json").read_text())["Type"] == "Brain"
    # the input is not in a BIDS dataset: no raw source to name
    assert "Sources" not in json.loads((anat / "sub-bp1_desc-tumorslices_mask.json").read_text())


def test_gifti_surfaces_are_the_ply_meshes_in_ras(published):
    _, base, _, _ = published
    anat = base / "bids" / "sub-bp1" / "anat"
    for gii, ply in (("sub-bp1_tumor.surf.gii", "sub-bp1_tumor.ply"),
                     ("sub-bp1_brain.surf.gii", "sub-bp1_brain.ply")):  # fmt: skip
        surf = nib.load(anat / gii)
        verts = surf.agg_data("NIFTI_INTENT_POINTSET")
        faces = surf.agg_data("NIFTI_INTENT_TRIANGLE")
        mesh = decode_ply((anat / ply).read_bytes())
        assert np.allclose(verts, mesh.vertices, atol=1e-3)
        assert np.array_equal(faces, mesh.faces)
        # scanner RAS, as the file says in words (code 3 would be Talairach)
        space = surf.darrays[0].coordsys
        scanner = nib.nifti1.xform_codes.code["scanner"]
        assert space.dataspace == space.xformspace == scanner == 1
        assert b"<DataSpace>NIFTI_XFORM_SCANNER_ANAT</DataSpace>" in (anat / gii).read_bytes()


def test_a_rerun_is_up_to_date_and_the_report_links_resolve(published):
    image, base, _, _ = published
    sub = base / "bids" / "sub-bp1"
    before = {p: p.stat().st_mtime_ns for p in sub.rglob("*")}
    again = run_patient(image, base / "bids", patient_id="bp1", store_dir=str(base / "store"),
                        layout="bids")  # fmt: skip
    assert again.up_to_date and all(again.cache_hits)
    assert {p: p.stat().st_mtime_ns for p in sub.rglob("*")} == before
    assert again.report["renders"]["anterior"] == "figures/sub-bp1_desc-anterior_render.png"
    assert unresolved_links(sub / "report.html") == []
    html = (sub / "report.html").read_text()
    assert "figures/sub-bp1_desc-tumor_overlay.png" in html


def test_an_id_that_is_no_bids_label_is_refused_naming_it(published, tmp_path):
    image, _, _, _ = published
    with pytest.raises(InputError, match="patient id 'bp-1' is not a BIDS participant label"):
        run_patient(image, tmp_path / "out", patient_id="bp-1", layout="bids",
                    store_dir=str(tmp_path / "store"))  # fmt: skip
    assert not (tmp_path / "out").exists() or not any(
        p for p in (tmp_path / "out").iterdir() if not p.name.startswith(".")
    )
    # the CLI: one line, exit 2, before Prefect starts
    result = CliRunner().invoke(
        app, ["run", str(image), "--out", str(tmp_path / "cli"), "--patient-id", "bp_1",
              "--layout", "bids"],
    )  # fmt: skip
    assert result.exit_code == 2, result.output
    assert "'bp_1' is not a BIDS participant label" in result.output
    assert "Traceback" not in result.output


def test_a_raw_dataset_description_is_never_replaced(published, tmp_path):
    image, _, _, _ = published
    raw = tmp_path / "raw"
    raw.mkdir()
    text = json.dumps({"Name": "my study", "BIDSVersion": "1.9.0"})
    (raw / "dataset_description.json").write_text(text)
    result = CliRunner().invoke(
        app, ["run", str(image), "--out", str(raw), "--patient-id", "bp1", "--layout", "bids"]
    )
    assert result.exit_code == 2, result.output
    assert "not a tumor3d derivative" in result.output
    assert (raw / "dataset_description.json").read_text() == text
    assert sorted(p.name for p in raw.iterdir()) == ["dataset_description.json"]


def test_an_input_in_a_bids_dataset_is_named_as_the_raw_source(published, tmp_path):
    image, base, _, _ = published
    raw = tmp_path / "study"
    (raw / "sub-07" / "anat").mkdir(parents=True)
    (raw / "dataset_description.json").write_text(
        json.dumps({"Name": "study", "BIDSVersion": "1.9.0", "DatasetDOI": "10.0/x"})
    )
    src = raw / "sub-07" / "anat" / "sub-07_T2w.nii.gz"
    shutil.copy(image, src)
    for sidecar in image.parent.glob(image.name.replace(".nii.gz", ".json")):
        shutil.copy(sidecar, src.with_name("sub-07_T2w.json"))
    out = raw / "derivatives" / "tumor3d"
    result = run_patient(src, out, store_dir=str(base / "store"), layout="bids")
    assert result.output_dir == str(out / "sub-07")  # the label of the BIDS file name
    desc = json.loads((out / "dataset_description.json").read_text())
    assert desc["DatasetLinks"] == {"raw": "../.."}  # relative: no path of this machine
    assert desc["SourceDatasets"][0]["DOI"] == "10.0/x"
    side = json.loads((out / "sub-07" / "anat" / "sub-07_desc-tumorslices_mask.json").read_text())
    assert side["Sources"] == ["bids:raw:sub-07/anat/sub-07_T2w.nii.gz"]
    assert (raw / "dataset_description.json").read_text().startswith('{"Name": "study"')


def test_a_cohort_in_the_bids_layout(published, tmp_path):
    from tumor3d.flows.cohort import run_cohort

    image, base, _, _ = published
    rows = [{"patient_id": "bp1", "image": str(image), "modality": "t2"}]
    out = tmp_path / "cohort"
    result = run_cohort(rows, out, workers=1, store_dir=str(base / "store"), layout="bids")
    assert result.exit_code in (0, 4), result.patients
    assert (out / "sub-bp1" / "anat" / "sub-bp1_desc-tumor_mask.nii.gz").is_file()
    assert json.loads((out / "dataset_description.json").read_text())["DatasetType"] == (
        "derivative"
    )
    page = (out / "cohort.html").read_text()
    assert 'href="sub-bp1/report.html"' in page
    assert 'src="sub-bp1/figures/sub-bp1_desc-anterior_render.png"' in page
    assert unresolved_links(out / "cohort.html") == []
    # before any work: a label that is not one, two ids on one label
    bad = [{"patient_id": "bp-1", "image": str(image), "modality": "t2"}]
    with pytest.raises(InputError, match="manifest row 1: patient id 'bp-1' is not a BIDS"):
        run_cohort(bad, tmp_path / "c2", store_dir=str(base / "store"), layout="bids")
    # either order names both ids and the folder (a user audit: 'p1' then 'sub-p1' was
    # called a duplicate patient_id 'sub-p1')
    for ids in (("sub-7", "7"), ("7", "sub-7")):
        twice = [{"patient_id": p, "image": str(image), "modality": "t2"} for p in ids]
        with pytest.raises(InputError, match=rf"^manifest row 2: patient_id '{ids[1]}' and "
                           rf"'{ids[0]}' \(row 1\) would both publish into sub-7$"):  # fmt: skip
            run_cohort(twice, tmp_path / "c3", store_dir=str(base / "store"), layout="bids")
    assert not (tmp_path / "c2").exists() and not (tmp_path / "c3").exists()


def test_a_default_folder_of_the_same_name_is_not_taken_as_current(published, tmp_path):
    """The layout is in the publish key: OUT/sub-bp1 of the default layout is republished."""
    image, base, _, _ = published
    store = str(base / "store")
    run_patient(image, tmp_path, patient_id="sub-bp1", store_dir=store)
    assert (tmp_path / "sub-bp1" / "tumor_mask.nii.gz").is_file()
    # the same id, so the same input, outputs and configuration: only the layout differs
    again = run_patient(image, tmp_path, patient_id="sub-bp1", store_dir=store, layout="bids")
    assert not again.up_to_date
    assert (tmp_path / "sub-bp1" / "anat" / "sub-bp1_desc-tumor_mask.nii.gz").is_file()
    assert not (tmp_path / "sub-bp1" / "tumor_mask.nii.gz").exists()


def test_the_cohort_command_refuses_an_id_that_is_no_label_in_one_line(published, tmp_path):
    image, _, _, _ = published
    manifest = tmp_path / "m.csv"
    manifest.write_text(f"patient_id,image,modality\nok1,{image},t2\npat_2,{image},t2\n")
    out = tmp_path / "out"
    result = CliRunner().invoke(
        app, ["cohort", str(manifest), "--out", str(out), "--layout", "bids"]
    )
    assert result.exit_code == 2, result.output
    assert "manifest row 2: patient id 'pat_2' is not a BIDS participant label" in result.output
    assert "Traceback" not in result.output
    assert not out.exists()  # a refused command leaves nothing (the folder was made empty)
    bad = CliRunner().invoke(app, ["cohort", str(manifest), "--out", str(out), "--layout", "x"])
    assert bad.exit_code == 2 and "--layout must be one of default, bids" in bad.output
