"""The single-patient flow end to end, under one temporary Prefect server.

Phantom patients with known truth go in as NIfTI or as a DICOM series; the
tests check what lands under ``<out>/<patient_id>/``, that a second run is
all cache hits, that a config change recomputes exactly the stages after it,
that no DICOM identity leaks into any file or log, and that a failing run
publishes nothing.
"""

from __future__ import annotations

import gzip
import io
import json
import logging
import re
import shutil
from pathlib import Path

import nibabel as nib
import numpy as np
import pandas as pd
import pytest
from headless_chromium import (
    local_links,
    needs_chromium,
    open_page,
    serious_console_messages,
    unresolved_links,
)
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian, MRImageStorage, generate_uid

from tumor3d.errors import InputError
from tumor3d.flows.patient import VOLUME_METHODS, run_patient
from tumor3d.geometry.surface import is_watertight, mesh_volume_mm3
from tumor3d.phantom import make_phantom_patient
from tumor3d.storage.formats import decode_ply
from tumor3d.storage.phantom_io import write_phantom_patient
from tumor3d.storage.viewer import NIIVUE_FILE
from tumor3d.tasks.stages import STAGES

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("prefect_harness")]

STAGE_NAMES = list(STAGES)
# Every name component is searched for on its own, so none may be a common word
# (a published file may contain "Private" in its embedded data, for example).
SECRET = {"PatientName": "Zzyzx^Quintessa^Vexqorit", "PatientID": "PHI-99331177",
          "PatientBirthDate": "19531207"}  # fmt: skip
# Small phantoms (128 x 128 pixels of 1.875 mm, the default field of view, 16 slices) for
# the runs whose question is not the image size (no tumour, a cut scan, DICOM identity and
# unreadable files): a run costs a third. The first run keeps the default phantom.
SMALL = {"n_slices": 16, "matrix_size": (128, 128)}


@pytest.fixture(scope="module")
def phantom():
    return make_phantom_patient(7, patient_id="flowpat")


@pytest.fixture(scope="module")
def nifti_input(phantom, tmp_path_factory):
    return write_phantom_patient(phantom, tmp_path_factory.mktemp("inputs")).image


@pytest.fixture(scope="module")
def first_run(nifti_input, tmp_path_factory):
    out = tmp_path_factory.mktemp("out")
    return out, run_patient(nifti_input, out, patient_id="flowpat", modality="t2")


def test_first_run_computes_every_stage_and_publishes_all_outputs(first_run, phantom):
    out, result = first_run
    assert [s.stage for s in result.stages] == STAGE_NAMES
    assert not any(result.cache_hits)
    folder = out / "flowpat"
    for name in ("tumor_mask_slices.nii.gz", "tumor_mask.nii.gz", "brain_mask.nii.gz",
                 "tumor.ply", "tumor_simplified.ply", "metrics.parquet", "slices.parquet",
                 "provenance.json"):  # fmt: skip
        assert (folder / name).is_file(), name
    assert (folder / "render_anterior.png").is_file()
    for name in ("tumor_lps.vtk", "viewer.html", "overlay_tumor.png", "overlay_brain.png",
                 "brain_mesh.ply", "render_turntable.gif"):  # fmt: skip
        assert (folder / name).is_file(), name
    html = (folder / "viewer.html").read_text()
    assert "<script" in html and 'src="http' not in html  # no network
    # the viewer's one script is shared by the output folder's patients
    assert f'src="../_assets/{NIIVUE_FILE}"' in html and (out / "_assets" / NIIVUE_FILE).is_file()
    # the LPS VTK surface is the RAS PLY surface with x and y negated
    import vtk
    from vtk.util.numpy_support import vtk_to_numpy

    from tumor3d.storage.formats import decode_ply

    reader = vtk.vtkPolyDataReader()
    reader.SetFileName(str(folder / "tumor_lps.vtk"))
    reader.Update()
    lps = vtk_to_numpy(reader.GetOutput().GetPoints().GetData())
    ras = decode_ply((folder / "tumor.ply").read_bytes()).vertices
    assert lps.shape == ras.shape
    assert np.allclose(lps, ras * np.array([-1.0, -1.0, 1.0]), atol=1e-4)
    # nothing half-written or staged is left beside the outputs
    assert not [p for p in out.iterdir() if p.name.startswith(".flowpat")]

    metrics = pd.read_parquet(folder / "metrics.parquet")
    required = {"patient_id", "volume_eq7_mm3", "volume_voxel_mm3", "volume_mesh_mm3",
                "n_slices", "n_abnormal_slices", "faces_mc", "faces_simplified",
                "volume_eq7_ce", "volume_eq7_ci95_low_mm3", "volume_eq7_ci95_high_mm3",
                "rano_longest_mm", "rano_perpendicular_mm", "max_diameter_3d_mm"}  # fmt: skip
    assert required <= set(metrics.columns)
    assert {f"time_{s.replace('-', '_')}_s" for s in STAGE_NAMES} <= set(metrics.columns)
    row = metrics.iloc[0]
    truth = phantom.true_volume_mm3
    for key in VOLUME_METHODS:
        assert abs(row[key] - truth) / truth < 0.10, key
        assert row[key.replace("_mm3", "_ml")] == pytest.approx(row[key] / 1000.0)
    assert row["n_slices"] == phantom.scan.n_slices
    assert 0 < row["faces_simplified"] < row["faces_mc"]


def test_published_masks_overlay_the_input(first_run, nifti_input, phantom):
    out, _ = first_run
    src = nib.load(nifti_input)
    seg = nib.load(out / "flowpat" / "tumor_mask_slices.nii.gz")
    assert seg.shape == src.shape
    np.testing.assert_array_equal(seg.affine, src.affine)
    seg_zyx = np.asarray(seg.dataobj).transpose(2, 1, 0) > 0
    inter = np.count_nonzero(seg_zyx & phantom.slice_masks)
    dice = 2 * inter / (seg_zyx.sum() + phantom.slice_masks.sum())
    assert dice > 0.9
    # The fine mask shares the world space: its RAS bounding box lies inside the
    # input's, and its voxels sit on the input's slice positions every m+1 slices.
    fine = nib.load(out / "flowpat" / "tumor_mask.nii.gz")
    corners = np.array([[0, 0, 0, 1], [*np.array(fine.shape) - 1, 1]], float)
    ras = corners @ fine.affine.T
    src_box = np.array([[0, 0, 0, 1], [*np.array(src.shape) - 1, 1]], float) @ src.affine.T
    lo, hi = src_box[:, :3].min(0) - 1e-6, src_box[:, :3].max(0) + 1e-6
    assert np.all(ras[:, :3] >= lo) and np.all(ras[:, :3] <= hi)


def test_mesh_is_closed_in_ras_and_matches_voxel_volume(first_run):
    out, result = first_run
    mesh = decode_ply((out / "flowpat" / "tumor.ply").read_bytes())
    assert is_watertight(mesh)
    voxel = result.metrics["volume_voxel_mm3"]
    assert abs(mesh_volume_mm3(mesh) - voxel) / voxel < 0.03
    assert b"SPACE=RAS" in (out / "flowpat" / "tumor.ply").read_bytes()[:300]


def test_provenance_records_versions_config_and_input_digest(first_run, phantom):
    out, result = first_run
    prov = json.loads((out / "flowpat" / "provenance.json").read_text())
    assert prov["versions"]["tumor3d"]
    assert prov["input"]["digest_sha256"] and len(prov["input"]["digest_sha256"]) == 64
    # the slab as read from the sidecar: the phantom's 2 mm slices every 5 mm
    scan = phantom.scan
    assert prov["input"]["slices"] == pytest.approx({
        "step_mm": scan.slice_step_mm, "thickness_mm": scan.slice_thickness_mm,
        "gap_mm": scan.slice_step_mm - scan.slice_thickness_mm})  # fmt: skip
    report = (out / "flowpat" / "report.html").read_text()
    assert f"Slice thickness</th><td class='num'>{scan.slice_thickness_mm:.2f} mm" in report
    assert prov["config"]["simplify"]["reduction_percent"] == 60.0
    assert [s["stage"] for s in prov["stages"]] == STAGE_NAMES


def test_second_run_is_all_cache_hits(first_run, nifti_input):
    out, first = first_run
    second = run_patient(nifti_input, out, patient_id="flowpat")
    assert all(second.cache_hits), [s.stage for s in second.stages if not s.cached]
    assert first.recomputed is None and second.recomputed is None  # new, then all hits
    for key in VOLUME_METHODS:
        assert second.metrics[key] == first.metrics[key]


def test_tampered_cached_result_is_detected_and_recomputed(first_run, nifti_input):
    """A digit changed in the cached measure result is caught by its digest, not published."""
    out, first = first_run
    value = first.metrics["volume_eq7_mm3"]
    needle = f'volume_eq7_mm3\\": {value!r}'
    results = out / ".tumor3d-store" / "prefect-results"
    hits = [f for f in results.iterdir() if f.is_file() and needle in f.read_text()]
    assert hits, "the measure stage's cached result was not found"
    for f in hits:
        text = f.read_text()
        first_digit = needle[-len(repr(value))]
        tampered = needle[: -len(repr(value))] + str((int(first_digit) + 1) % 10) + repr(value)[1:]
        f.write_text(text.replace(needle, tampered))
    again = run_patient(nifti_input, out, patient_id="flowpat")
    measure = again.stages[-1]
    assert measure.stage == "measure-volume" and not measure.cached
    assert "digest" in measure.repaired
    assert all(again.cache_hits[:-1])
    for key in VOLUME_METHODS:
        assert again.metrics[key] == first.metrics[key]
    published = pd.read_parquet(out / "flowpat" / "metrics.parquet").iloc[0]
    assert published["volume_eq7_mm3"] == value
    prov = json.loads((out / "flowpat" / "provenance.json").read_text())
    assert "digest" in prov["stages"][-1]["repaired"]
    # the repair rewrote the cached result: the next run is all hits again
    assert all(run_patient(nifti_input, out, patient_id="flowpat").cache_hits)


def test_output_folder_holding_the_input_is_refused(tmp_path, phantom):
    image = write_phantom_patient(phantom, tmp_path / "O" / "pat1").image
    with pytest.raises(InputError, match="would delete the input"):
        run_patient(image, tmp_path / "O", patient_id="pat1")
    assert image.is_file()
    assert sorted(p.name for p in (tmp_path / "O").iterdir()) == ["pat1"]


def test_tumour_free_patient_writes_no_empty_mesh_and_says_so(tmp_path):
    patient = make_phantom_patient(1, tumor=False, patient_id="clear1", **SMALL)
    image = write_phantom_patient(patient, tmp_path / "in").image
    result = run_patient(image, tmp_path / "out", patient_id="clear1")
    folder = tmp_path / "out" / "clear1"
    assert not list(folder.glob("tumor*.ply")) and not list(folder.glob("render_*"))
    assert (folder / "viewer.html").is_file()  # the slices, to check what was missed
    assert (folder / "brain_mesh.ply").is_file()  # the brain is there all the same
    assert (folder / "tumor_mask.nii.gz").is_file()
    # the report says so, shows the overlays and links nothing that is not there
    page = (folder / "report.html").read_text()
    assert "no tumour found" in page and "overlay_brain.png" in page
    assert unresolved_links(folder / "report.html") == []
    # the slice overlays are written all the same: they show what was (not) found
    assert (folder / "overlay_brain.png").is_file() and (folder / "overlay_tumor.png").is_file()
    metrics = pd.read_parquet(folder / "metrics.parquet").iloc[0]
    assert metrics["volume_eq7_mm3"] == 0.0 and not metrics["tumour_found"]
    assert "no tumour found" in metrics["notes"]
    assert "no tumour found" in json.loads((folder / "provenance.json").read_text())["notes"][0]
    assert result.notes and "no tumour found" in result.notes[0]
    # an empty result asks a human to confirm there is none (a missed tumour looks the same)
    assert metrics["status"] == "check" and metrics["needs_review"]
    assert metrics["review_reasons"].startswith("no tumour found: confirm")


def test_tumour_cut_by_the_end_of_the_scan_is_named_in_the_notes(tmp_path, first_run):
    # the whole phantom's tumour lies inside its scan: nothing to say, status ok
    assert not any("slice of the scan" in n for n in first_run[1].notes)
    assert first_run[1].metrics["status"] == "ok"
    # the same phantom (small) scanned only up to its tumour's middle slice
    small = make_phantom_patient(7, patient_id="flowpat", **SMALL)
    image = write_phantom_patient(small, tmp_path / "in").image
    src = nib.load(image)
    z_axis = list(np.argsort(small.scan.source_grid.axes)).index(2)
    tumour_z = np.flatnonzero(small.slice_masks.any(axis=(1, 2)))
    keep = int(tumour_z[0] + tumour_z[-1]) // 2 + 1
    cut = np.take(np.asarray(src.dataobj), np.arange(keep), axis=z_axis)
    nib.save(nib.Nifti1Image(cut, src.affine, src.header), image)
    result = run_patient(image, tmp_path / "out", patient_id="cut1")
    note = [n for n in result.notes if "slice of the scan" in n]
    assert len(note) == 1 and "underestimate" in note[0]
    assert f"last slice of the scan (slice {keep - 1}, 0-based)" in note[0]
    folder = tmp_path / "out" / "cut1"
    assert note[0] in pd.read_parquet(folder / "metrics.parquet").iloc[0]["notes"]
    assert note[0] in json.loads((folder / "provenance.json").read_text())["notes"]
    # the tool's own caveat asks for a human: status check, never a green ok (issue 33)
    metrics = pd.read_parquet(folder / "metrics.parquet").iloc[0]
    assert metrics["status"] == "check" and metrics["needs_review"]
    assert note[0] in metrics["review_reasons"]
    assert '<strong class="status-check">check</strong>' in (folder / "report.html").read_text()


@pytest.mark.parametrize(
    ("config", "first_changed"),
    [
        ({"simplify": {"reduction_percent": 40}}, "simplify-mesh"),
        ({"interpolate": {"method": "shape"}}, "interpolate-slices"),
        # the brain surface is its own stage, before the renders: a new render
        # setting reuses it (it used to be recomputed inside every render)
        ({"render": {"width": 320, "turntable_frames": 4}}, "render-views"),
    ],
)
def test_config_change_recomputes_that_stage_and_later_only(
    first_run, nifti_input, config, first_changed
):
    out, _ = first_run
    result = run_patient(nifti_input, out, patient_id="flowpat", config=config)
    k = STAGE_NAMES.index(first_changed)
    hits = result.cache_hits
    # the folder held the result of another configuration (the default's, or the case
    # before's): the run says why stages ran again
    assert result.recomputed == "configuration changed"
    assert all(hits[:k]), "stages before the changed one must be cache hits"
    assert not hits[k], "the changed stage must recompute"
    assert hits[STAGE_NAMES.index("extract-brain-surface")], "the brain surface is reused"
    if first_changed == "render-views":
        assert hits[-1]  # the volumes do not depend on the renders
    else:
        assert not hits[STAGE_NAMES.index("render-views")]  # a new tumour surface
        # stages after it see new inputs (measure-volume always depends on the mesh)
        assert not hits[-1]


def _write_dicom_series(patient, folder):
    """An axial DICOM series of a phantom, carrying a known patient identity."""
    scan = patient.scan
    folder.mkdir(parents=True)
    aff = scan.affine  # (x, y, z, 1) -> RAS, x to the patient's left, y posterior
    lps = np.diag([-1.0, -1.0, 1.0]) @ aff[:3, :3]
    row_dir = lps[:, 0] / np.linalg.norm(lps[:, 0])
    col_dir = lps[:, 1] / np.linalg.norm(lps[:, 1])
    dy, dx = scan.pixel_spacing_mm
    series_uid = generate_uid()
    scale = 30000.0 / float(scan.image.max())
    for k in range(scan.n_slices):
        origin = np.diag([-1.0, -1.0, 1.0]) @ (aff @ [0, 0, k, 1])[:3]
        meta = FileMetaDataset()
        meta.MediaStorageSOPClassUID = MRImageStorage
        meta.MediaStorageSOPInstanceUID = generate_uid()
        meta.TransferSyntaxUID = ExplicitVRLittleEndian
        ds = Dataset()
        ds.file_meta = meta
        ds.SOPClassUID = MRImageStorage
        ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
        ds.SeriesInstanceUID = series_uid
        ds.StudyInstanceUID = generate_uid()
        ds.Modality = "MR"
        ds.SeriesDescription = "T2 AX"
        for key, value in SECRET.items():
            setattr(ds, key, value)
        ds.InstanceNumber = k + 1
        ds.ImageOrientationPatient = [f"{v:.6f}" for v in (*row_dir, *col_dir)]
        ds.ImagePositionPatient = [f"{v:.6f}" for v in origin]
        ds.PixelSpacing = [f"{dy:.6f}", f"{dx:.6f}"]
        ds.SliceThickness = f"{scan.slice_thickness_mm:.3f}"
        ds.RescaleSlope, ds.RescaleIntercept = f"{1 / scale:.9f}", "0"
        ds.Rows, ds.Columns = scan.shape[1], scan.shape[2]
        ds.SamplesPerPixel, ds.PhotometricInterpretation = 1, "MONOCHROME2"
        ds.BitsAllocated, ds.BitsStored, ds.HighBit, ds.PixelRepresentation = 16, 16, 15, 1
        ds.PixelData = np.round(scan.image[k] * scale).astype("<i2").tobytes()
        ds.save_as(folder / f"slice{(k * 7) % scan.n_slices:03d}.dcm", enforce_file_format=True)


def _readable_text(path):
    """A file's content as searchable bytes: decompressed and decoded where needed."""
    data = path.read_bytes()
    if path.name.endswith(".gz"):
        data = gzip.decompress(data)
    if path.suffix == ".parquet":
        data = pd.read_parquet(io.BytesIO(data)).to_csv().encode()
    return data


@pytest.fixture(scope="module")
def dicom_series(tmp_path_factory):
    """A DICOM series of a small phantom carrying :data:`SECRET`; the folder for the
    identity test's output, whose store the unreadable-file test reuses."""
    patient = make_phantom_patient(3, patient_id="dcmsrc", **SMALL)
    base = tmp_path_factory.mktemp("dicom")
    _write_dicom_series(patient, base / "series")
    return patient, base / "series", base / "out"


def test_dicom_identity_never_reaches_outputs_or_logs(dicom_series, caplog, capfd):
    _, series, out = dicom_series
    with caplog.at_level(logging.DEBUG):
        result = run_patient(series, out)
    assert result.patient_id == "series"  # from the folder name, never from the DICOM
    assert result.metrics["n_tumor_slices"] > 0
    captured = capfd.readouterr()
    logs = caplog.text + captured.out + captured.err
    for value in SECRET.values():
        needles = {value, value.replace("^", " "), *value.split("^")}
        for needle in needles:
            assert needle not in logs
            for f in out.rglob("*"):
                if f.is_file():
                    assert needle.encode() not in _readable_text(f), (needle, f)


def test_failure_inside_the_flow_publishes_nothing(tmp_path):
    bad = tmp_path / "zeros.nii.gz"
    nib.save(nib.Nifti1Image(np.zeros((16, 16, 6), np.float32), np.eye(4)), bad)
    out = tmp_path / "out"
    with pytest.raises(InputError, match="all-zero"):
        run_patient(bad, out, patient_id="p1")
    assert not (out / "p1").exists()
    assert not [p for p in out.iterdir() if p.name.startswith(".p1")]


def test_unreadable_dicom_file_stops_the_run_unless_skipped_and_then_is_named(
    dicom_series, tmp_path
):
    patient, source, identity_out = dicom_series
    series = tmp_path / "series"
    shutil.copytree(source, series)
    # a file of random bytes among the slices (sorted last by name: an end slice)
    (series / "zz_corrupt.dcm").write_bytes(np.random.default_rng(0).bytes(4096))
    with pytest.raises(InputError, match="zz_corrupt.dcm"):
        run_patient(series, tmp_path / "out")
    assert not (tmp_path / "out" / "series").exists()
    # the ingest stage reads the series again (the skip and the folder are in its key);
    # the stages after it may come from the identity test's store (the same slices)
    store = str(identity_out / ".tumor3d-store")
    result = run_patient(series, tmp_path / "out", skip_unreadable=True, store_dir=store)
    assert not result.stages[0].cached
    assert result.metrics["n_slices"] == patient.scan.n_slices  # every real slice read
    assert any("zz_corrupt.dcm" in n for n in result.notes), result.notes
    metrics = pd.read_parquet(Path(result.output_dir) / "metrics.parquet").iloc[0]
    assert "zz_corrupt.dcm" in metrics["notes"]
    provenance = json.loads((Path(result.output_dir) / "provenance.json").read_text())
    assert any("zz_corrupt.dcm" in n for n in provenance["notes"])


def test_report_links_only_files_beside_it_and_shows_the_metrics(first_run, tmp_path):
    out, result = first_run
    folder = out / "flowpat"
    # relative links: the folder still works after a move
    moved = tmp_path / "elsewhere" / "flowpat"
    shutil.copytree(folder, moved)
    assert unresolved_links(moved / "report.html") == []
    targets = set(local_links(folder / "report.html"))
    expected = {f"render_{v}.png" for v in ("anterior", "posterior", "right", "left",
                                              "superior", "inferior", "cut_axial",
                                              "cut_coronal")}  # fmt: skip
    expected |= {"render_turntable.gif", "overlay_tumor.png", "overlay_brain.png", "viewer.html"}
    assert targets == expected
    page = (folder / "report.html").read_text()
    row = pd.read_parquet(folder / "metrics.parquet").iloc[0]
    for key in ("volume_eq7", "volume_voxel", "volume_mesh"):
        assert f"{row[key + '_mm3']:,.1f}" in page and f"{row[key + '_ml']:,.3f}" in page
    lo, hi = row["volume_eq7_ci95_low_mm3"], row["volume_eq7_ci95_high_mm3"]
    assert lo < row["volume_eq7_mm3"] < hi
    assert f"{lo:,.1f} to {hi:,.1f} (CE {100 * row['volume_eq7_ce']:.1f} %)" in page
    assert f"{row['rano_longest_mm']:.1f} mm" in page
    assert f"<td class='num'>{int(row['faces_mc'])}</td>" in page
    assert f"<td class='num'>{int(row['faces_simplified'])}</td>" in page
    # the report in the result is what the page was built from
    assert result.report["patient_id"] == "flowpat"
    assert result.report["volumes_mm3"]["eq7"] == pytest.approx(row["volume_eq7_mm3"])


@needs_chromium
def test_published_report_loads_in_headless_chromium(first_run, tmp_path):
    out, _ = first_run
    moved = tmp_path / "moved" / "flowpat"
    shutil.copytree(out / "flowpat", moved)
    page = open_page(moved / "report.html", tmp_path, size=(1100, 2400), budget_ms=5000)
    assert page.js_errors == []
    assert serious_console_messages(page.console) == []
    assert len(page.images) == 11  # 8 renders, the turntable, two overlays
    assert all(width > 0 for _, width in page.images), page.images
    # the renders are on screen: the red tumour shows
    shot = page.screenshot.astype(int)
    red = (shot[..., 0] > shot[..., 1] + 40) & (shot[..., 0] > shot[..., 2] + 40)
    assert red.sum() > 500, red.sum()


@needs_chromium
def test_published_viewer_shows_the_published_masks(first_run, tmp_path):
    out, _ = first_run
    for name in ("flowpat", "_assets"):  # a copy: the browser harness writes beside the page
        shutil.copytree(out / name, tmp_path / "out" / name)
    page = open_page(tmp_path / "out" / "flowpat" / "viewer.html", tmp_path, budget_ms=8000)
    assert page.js_errors == []
    assert serious_console_messages(page.console) == []
    status = re.search(r'<p id="t3d-status"([^>]*)>', page.dom)
    attrs = dict(re.findall(r'(data-[\w-]+)="([^"]*)"', status.group(1)))
    assert attrs["data-state"] == "ready", page.dom[-2000:]
    # the page holds every voxel of the published masks (cropped, never cut)
    for key, name in (
        ("data-tumour-voxels", "tumor_mask_slices"),
        ("data-brain-voxels", "brain_mask"),
    ):
        published = np.asanyarray(nib.load(out / "flowpat" / f"{name}.nii.gz").dataobj) > 0
        assert int(attrs[key]) == int(published.sum()) > 0, name
    assert attrs["data-meshes"] == "tumour surface,brain surface"


def test_summary_artifacts_are_on_the_patient_flow_run(first_run):
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import ArtifactFilter, ArtifactFilterKey

    out, _ = first_run
    keys = ["tumor3d-flowpat-summary", "tumor3d-flowpat-table"]
    with get_client(sync_client=True) as client:
        arts = client.read_artifacts(
            artifact_filter=ArtifactFilter(key=ArtifactFilterKey(any_=keys))
        )
        assert {a.key for a in arts} == set(keys)
        for art in arts:
            assert client.read_flow_run(art.flow_run_id).name == "patient-flowpat"
    md = next(a for a in arts if a.key == keys[0]).data
    row = pd.read_parquet(out / "flowpat" / "metrics.parquet").iloc[0]
    assert f"| Eq. 7 (slab sum) | {row['volume_eq7_mm3']:,.1f} | {row['volume_eq7_ml']:.3f} |" in md


def test_run_name_is_the_patient_id_derived_from_the_file(nifti_input, first_run, tmp_path):
    """Issue 33: the run is named after the id it publishes under, not the file name."""
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import FlowRunFilter, FlowRunFilterName

    store = str(first_run[0] / ".tumor3d-store")  # the stages from the first run's cache
    result = run_patient(nifti_input, tmp_path / "out", store_dir=store)  # id from the name
    assert result.patient_id == "flowpat_t2" and nifti_input.name == "flowpat_t2.nii.gz"
    with get_client(sync_client=True) as client:
        names = FlowRunFilter(
            name=FlowRunFilterName(any_=["patient-flowpat_t2", "patient-flowpat_t2.nii.gz"])
        )
        runs = client.read_flow_runs(flow_run_filter=names)
    assert {r.name for r in runs} == {"patient-flowpat_t2"}
