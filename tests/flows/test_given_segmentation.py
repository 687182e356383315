"""A given tumour segmentation (``tumor3d run --segmentation``, issue 33) end to end.

One phantom, one shared store, through the command line: the phantom's true
slice mask given as a 0/255 NIfTI replaces the segment-tumor stage, so Eq. 7
must equal the truth computed here independently (mask pixels x pixel area x
slab height); the mask file is never modified; a second run is all cache
hits; a mask of other content recomputes segment-tumor and every stage after
it (the scan, preprocess and detection are reused), and a tumour on a slice
the detection does not flag is kept. Masks off the image's grid are refused
in one line naming the file, before any work.
"""

from __future__ import annotations

import hashlib
import json
import struct

import nibabel as nib
import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from tumor3d.flows.cli import app
from tumor3d.phantom import make_phantom_patient
from tumor3d.storage.formats import decode_ply
from tumor3d.storage.phantom_io import write_phantom_patient
from tumor3d.tasks.stages import STAGES

runner = CliRunner()
STAGE_NAMES = list(STAGES)
AFTER_SEGMENT = STAGE_NAMES[STAGE_NAMES.index("segment-tumor") :]


def _sha(path):
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _save(path, mask_zyx, affine, scale=255):
    """A mask in the image's NIfTI voxel order (x, y, z)."""
    data = (np.asarray(mask_zyx).transpose(2, 1, 0) * scale).astype(np.uint8)
    nib.save(nib.Nifti1Image(data, affine), path)
    return path


def _truth_eq7_mm3(mask_zyx, scan):
    """Eq. 7 by hand: tumour pixels x pixel area x slab height (thickness + gap)."""
    dy, dx = scan.pixel_spacing_mm
    return float(np.sum(mask_zyx)) * dy * dx * (scan.slice_thickness_mm + scan.slice_gap_mm)


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("seg-in")
    patient = make_phantom_patient(5, patient_id="segpat", n_slices=16)
    image = write_phantom_patient(patient, tmp).image
    affine = nib.load(image).affine
    truth = patient.slice_masks.astype(bool)
    return {
        "patient": patient, "image": image, "affine": affine, "truth": truth,
        "mask": _save(tmp / "my_seg.nii.gz", truth, affine),
        "store": tmp_path_factory.mktemp("seg-store"), "tmp": tmp,
    }  # fmt: skip


def _run(case, out, mask, *extra):
    args = ["run", str(case["image"]), "--out", str(out), "--patient-id", "segpat"]
    args += ["--modality", "t2", "--store", str(case["store"]), "--segmentation", str(mask)]
    return runner.invoke(app, [*args, *extra])


def _metrics(out):
    return pd.read_parquet(out / "segpat" / "metrics.parquet").iloc[0]


def _cached(row):
    return {s: bool(row[f"cached_{s.replace('-', '_')}"]) for s in STAGE_NAMES}


@pytest.fixture(scope="module")
def first(case, tmp_path_factory, prefect_harness):
    out = tmp_path_factory.mktemp("seg-out")
    before = _sha(case["mask"])
    res = _run(case, out, case["mask"])
    assert res.exit_code == 0, res.output
    return {"out": out, "output": res.output, "sha_before": before}


@pytest.mark.slow
def test_the_true_mask_gives_eq7_equal_to_the_truth(case, first):
    row = _metrics(first["out"])
    expected = _truth_eq7_mm3(case["truth"], case["patient"].scan)
    assert expected > 1000.0  # a real tumour, not an empty mask
    assert row["volume_eq7_mm3"] == pytest.approx(expected, rel=1e-9)
    assert row["segment_method"] == "given"
    assert row["measured"] == "the segmentation given by the user (my_seg.nii.gz)"
    assert row["status"] == "ok"
    # the published slice mask is the given one, voxel for voxel
    published = np.asarray(nib.load(first["out"] / "segpat" / "tumor_mask_slices.nii.gz").dataobj)
    np.testing.assert_array_equal(published.transpose(2, 1, 0) > 0, case["truth"])
    # the voxel and mesh volumes come from the same mask: close to Eq. 7
    assert row["volume_voxel_mm3"] == pytest.approx(expected, rel=0.25)


@pytest.mark.slow
def test_the_mask_file_is_never_modified_and_provenance_records_it(case, first):
    assert _sha(case["mask"]) == first["sha_before"]
    folder = first["out"] / "segpat"
    prov = json.loads((folder / "provenance.json").read_text())
    assert prov["segmentation"]["given"] is True
    assert prov["segmentation"]["file"] == "my_seg.nii.gz"
    assert prov["segmentation"]["sha256"] == first["sha_before"]
    assert prov["segmentation"]["tumour_voxels"] == int(case["truth"].sum())
    assert "segmentation: given (my_seg.nii.gz" in (folder / "report.html").read_text()
    assert "segmentation: given (my_seg.nii.gz" in " ".join(first["output"].split())


@pytest.mark.slow
def test_stl_files_are_written_in_lps(first):
    folder = first["out"] / "segpat"
    row = _metrics(first["out"])
    for name, faces in (("tumor.stl", "faces_mc"), ("tumor_simplified.stl", "faces_simplified")):
        data = (folder / name).read_bytes()
        assert data[:9] == b"SPACE=LPS", name
        n = struct.unpack("<I", data[80:84])[0]
        assert n == int(row[faces]) > 0 and len(data) == 84 + 50 * n
    # the STL holds the RAS PLY's surface in LPS: x and y negated, z kept
    ply = decode_ply((folder / "tumor.ply").read_bytes())
    facet = np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")])
    stl = np.frombuffer((folder / "tumor.stl").read_bytes()[84:], dtype=facet)["v"].reshape(-1, 3)
    lps = ply.vertices * np.array([-1.0, -1.0, 1.0])
    np.testing.assert_allclose(stl.min(axis=0), lps.min(axis=0), atol=1e-3)
    np.testing.assert_allclose(stl.max(axis=0), lps.max(axis=0), atol=1e-3)


@pytest.mark.slow
def test_a_second_run_is_all_cache_hits_and_another_mask_recomputes(case, first, tmp_path):
    out = first["out"]
    again = _run(case, out, case["mask"])
    assert again.exit_code == 0, again.output
    # every stage a cache hit: the folder already holds this result (its metrics are the
    # first run's), so the progress lines (one a stage, stdout not a terminal) say it
    hits = [s for s in STAGE_NAMES if f"segpat\t{s}\tcache hit" in again.output]
    assert hits == STAGE_NAMES, again.output
    assert "up to date" in again.output
    # other content: one tumour slice dropped, one blob on a slice without tumour
    # (and, most likely, not flagged abnormal): the blob is kept, Eq. 7 follows the mask
    edited = case["truth"].copy()
    slices = np.flatnonzero(edited.any(axis=(1, 2)))
    edited[slices[-1]] = False
    empty = [z for z in range(edited.shape[0]) if not case["truth"][z].any()]
    z0 = empty[len(empty) // 2]
    ys, xs = np.nonzero(case["truth"][slices[len(slices) // 2]])
    cy, cx = int(ys.mean()), int(xs.mean())
    edited[z0, cy - 3 : cy + 4, cx - 3 : cx + 4] = True
    other = _save(tmp_path / "edited_seg.nii.gz", edited, case["affine"], scale=1)
    res = _run(case, out, other)
    assert res.exit_code in (0, 4), res.output
    row = _metrics(out)
    cached = _cached(row)
    assert [cached[s] for s in STAGE_NAMES if s not in AFTER_SEGMENT] == [True, True, True]
    assert not cached["segment-tumor"] and not cached["interpolate-slices"]
    assert row["volume_eq7_mm3"] == pytest.approx(
        _truth_eq7_mm3(edited, case["patient"].scan), rel=1e-9
    )
    published = np.asarray(nib.load(out / "segpat" / "tumor_mask_slices.nii.gz").dataobj)
    assert published.transpose(2, 1, 0)[z0].sum() == 49


# ------------------------------------------------------------ refused before any work


def _shifted(affine, voxels=3.0):
    moved = np.asarray(affine, dtype=np.float64).copy()
    moved[:3, 3] += moved[:3, 0] * voxels  # three voxels along the first axis
    return moved


@pytest.mark.parametrize(
    ("kind", "message"),
    [("shape", "segmentation: shape"), ("affine", "segmentation: affine")],
)
def test_a_mask_off_the_image_grid_is_one_line_naming_the_file(case, tmp_path, kind, message):
    truth = case["truth"]
    if kind == "shape":
        bad = _save(tmp_path / "bad_seg.nii.gz", truth[:-1], case["affine"])
    else:
        bad = _save(tmp_path / "bad_seg.nii.gz", truth, _shifted(case["affine"]))
    out = tmp_path / "out"
    res = _run(case, out, bad)
    assert res.exit_code == 2, res.output
    assert f"error: {bad}: {message}" in res.output, res.output
    assert "differs from the image's" in res.output
    assert len(res.output.strip().splitlines()) == 1, res.output
    assert "Traceback" not in res.output and "starting Prefect" not in res.output
    assert not out.exists() or not any(out.iterdir())


def test_a_mask_inside_the_output_folder_is_refused(case, tmp_path):
    inside = tmp_path / "out" / "segpat"
    inside.mkdir(parents=True)
    mask = _save(inside / "seg.nii.gz", case["truth"], case["affine"])
    res = _run(case, tmp_path / "out", mask)
    assert res.exit_code == 2, res.output
    assert "would delete the input" in res.output and mask.is_file()


def test_segmentation_option_is_in_the_help_of_run():
    assert "--segmentation" in runner.invoke(app, ["run", "--help"]).output
