"""A given tumour segmentation through the Python API and the core rules (issue 33)."""

from __future__ import annotations

import nibabel as nib
import numpy as np
import pytest

import tumor3d
from tumor3d.errors import InputError
from tumor3d.phantom import make_phantom_patient
from tumor3d.segmentation.given_segmentation import binarize_segmentation, given_segmentation
from tumor3d.storage.phantom_io import write_phantom_patient


@pytest.fixture(scope="module")
def case(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("api-seg")
    patient = make_phantom_patient(5, patient_id="apiseg", n_slices=16)
    image = write_phantom_patient(patient, tmp).image
    affine = nib.load(image).affine
    truth = patient.slice_masks.astype(bool)
    mask = tmp / "seg.nii.gz"
    nib.save(nib.Nifti1Image(truth.transpose(2, 1, 0).astype(np.uint8), affine), mask)
    s = patient.scan
    dy, dx = s.pixel_spacing_mm
    eq7 = float(truth.sum()) * dy * dx * (s.slice_thickness_mm + s.slice_gap_mm)
    return {"image": image, "affine": affine, "truth": truth, "mask": mask, "eq7": eq7}


def test_reconstruct_with_a_given_file_measures_that_mask(case):
    r = tumor3d.reconstruct(case["image"], modality="t2", segmentation=case["mask"])
    assert r.method == "given"
    assert r.measured == "the segmentation given by the user (seg.nii.gz)"
    np.testing.assert_array_equal(r.tumor_mask_slices, case["truth"])
    assert r.volumes_mm3["eq7"] == pytest.approx(case["eq7"], rel=1e-9)
    assert "segmentation: given (seg.nii.gz)" in r.notes
    assert r.eq7_ce > 0 and r.eq7_ci95_mm3[0] < case["eq7"] < r.eq7_ci95_mm3[1]


def test_reconstruct_with_an_array_in_file_order(case):
    data = np.asarray(nib.load(case["image"]).dataobj)
    seg = case["truth"].transpose(2, 1, 0).astype(np.float32) * 0.9  # a probability map
    r = tumor3d.reconstruct(data, affine=case["affine"], modality="t2", segmentation=seg)
    assert r.method == "given"
    assert r.volumes_mm3["eq7"] == pytest.approx(case["eq7"], rel=1e-9)


def test_a_file_off_the_grid_is_one_line_naming_it(case, tmp_path):
    bad = tmp_path / "short.nii.gz"
    data = case["truth"][:-1].transpose(2, 1, 0).astype(np.uint8)
    nib.save(nib.Nifti1Image(data, case["affine"]), bad)
    with pytest.raises(InputError) as err:
        tumor3d.reconstruct(case["image"], modality="t2", segmentation=bad)
    text = str(err.value)
    assert str(bad) in text and "segmentation: shape" in text and "\n" not in text


def test_rules_threshold_and_refusals():
    values = np.zeros((3, 4, 4), np.float32)
    values[1, 1:3, 1:3] = [[0.5, 0.51], [255, 1]]
    mask = binarize_segmentation(values)
    assert mask.sum() == 3 and not mask[1, 1, 1]
    values[0, 0, 0] = np.nan
    with pytest.raises(InputError, match="NaN or infinite"):
        binarize_segmentation(values)
    res = given_segmentation(mask)
    assert res.method == "given" and list(res.tumor_pixels) == [0, 3, 0]
    assert list(res.selection) == ["", "given", ""]
    assert res.caveats == ()  # nothing on the first or last slice
    edge = given_segmentation(np.roll(mask, 1, axis=0))
    assert any("last slice" in c for c in edge.caveats)
