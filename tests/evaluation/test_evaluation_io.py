"""tumor3d.storage.evaluation_io: preparing manifest rows for evaluation (bad input, emulation)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.storage import nifti
from tumor3d.storage.evaluation_io import prepare_case, reference_mask
from tumor3d.storage.manifest import ManifestRow
from tumor3d.storage.readers import read_nifti_scan


def _write(path, array, affine, dtype="float32"):
    path.write_bytes(nifti.encode_nifti(array, affine, dtype=dtype))
    return path


@pytest.fixture
def thin(tmp_path):
    """A 1 mm 'thin' image 12x10x20 (slice axis 2) and a label with values 1 and 2."""
    rng = np.random.default_rng(0)
    img = (rng.random((12, 10, 20)) * 100 + 10).astype(np.float32)
    aff = np.diag([-1.0, -1.0, 1.0, 1.0])
    lab = np.zeros((12, 10, 20), np.uint8)
    lab[3:7, 3:6, 4:12] = 2
    lab[4:6, 4:5, 6:9] = 1
    return (
        _write(tmp_path / "img.nii.gz", img, aff),
        _write(tmp_path / "seg.nii.gz", lab, aff, "uint8"),
        img,
        lab,
        aff,
    )


def test_emulated_image_and_sidecar_read_back_as_thick_slices(thin, tmp_path):
    image, seg, img, _, aff = thin
    row = ManifestRow(
        "p1", image, "t2", reference=seg, reference_labels=(1, 2),
        emulate_step_mm=5.0, emulate_thickness_mm=2.0, reference_kind="expert",
    )  # fmt: skip
    prep = prepare_case(row, tmp_path / "emu")
    assert prep.acquisition == "emulated 2 mm every 5 mm"
    assert prep.run_row.image.parent == (tmp_path / "emu" / "p1").resolve()
    assert prep.run_row.emulate_step_mm is None
    meta = json.loads(prep.run_row.image.with_name("p1_t2.json").read_text())
    assert (meta["SliceThickness"], meta["SpacingBetweenSlices"]) == (2.0, 5.0)
    scan = read_nifti_scan(prep.run_row.image)  # the reader honours the sidecar
    assert scan.n_slices == 4  # thin 0-1, 5-6, 10-11, 15-16
    assert (scan.slice_step_mm, scan.slice_thickness_mm, scan.slice_gap_mm) == (5.0, 2.0, 3.0)
    back, back_aff = nifti.read_nifti(prep.run_row.image)
    np.testing.assert_allclose(back[:, :, 1], img[:, :, 5:7].mean(axis=2), rtol=1e-6)
    np.testing.assert_allclose(back_aff[:3, 3], aff[:3, 3] + [0, 0, 0.5])
    assert prep.emulation["thin_indices"][1] == [5, 6]


def test_native_row_and_label_selection(thin, tmp_path):
    image, seg, _, lab, _ = thin
    prep = prepare_case(ManifestRow("p1", image, "t2", reference=seg), tmp_path)
    assert prep.acquisition.startswith("native, 1 mm") and prep.reference_kind == "unspecified"
    only1 = ManifestRow("p1", image, "t2", reference=seg, reference_labels=(1,))
    mask, _ = reference_mask(only1)
    assert mask.sum() == (lab == 1).sum()


@pytest.mark.parametrize("dtype", ["uint8", "int16", "float32"])
def test_the_mask_does_not_depend_on_the_labels_storage_type(thin, tmp_path, dtype):
    image, _, _, lab, aff = thin
    seg = _write(tmp_path / f"seg_{dtype}.nii.gz", lab, aff, dtype)
    for labels, expected in (((1,), lab == 1), ((2,), lab == 2), (None, lab > 0)):
        mask, _ = reference_mask(ManifestRow("p1", image, "t2", reference=seg,
                                             reference_labels=labels))  # fmt: skip
        assert mask.dtype == bool and np.array_equal(mask, expected), (dtype, labels)


@pytest.mark.parametrize(
    ("value", "message"), [(1.5, "labels are not integers"), (np.nan, "has non-finite values")]
)
def test_float_labels_that_are_not_integers_are_refused(thin, tmp_path, value, message):
    image, _, _, lab, aff = thin
    bad = lab.astype(np.float32)
    bad[0, 0, 0] = value
    seg = _write(tmp_path / "bad.nii.gz", bad, aff, "float32")
    with pytest.raises(InputError, match=f"patient p5: the reference {message}"):
        reference_mask(ManifestRow("p5", image, "t2", reference=seg))


def test_an_image_given_as_the_reference_is_refused(thin, tmp_path):
    """A scan's gray levels given as the reference (integers, so no other check objects)
    made nearly every voxel tumour: ``train`` then learned from it (a user audit: 6,000 of
    6,268 rows lesion) and ``evaluate`` would score against it. A label map has a few
    values (BraTS: 4 labels and 0)."""
    image, seg, img, lab, aff = thin
    gray = _write(tmp_path / "flair.nii.gz", np.rint(img).astype(np.int16), aff, "int16")
    with pytest.raises(InputError) as exc:
        reference_mask(ManifestRow("p6", image, "t2", reference=gray))
    text = str(exc.value)
    assert text.startswith(f"{gray}: patient p6: the reference holds ")
    assert "distinct values (10-110): an image, not a label map (at most 32 labels)" in text
    many = lab.astype(np.int16)
    many[0, 0, :20] = np.arange(20) + 100  # 20 labels more: still a label map
    ok = _write(tmp_path / "many.nii.gz", many, aff, "int16")
    assert reference_mask(ManifestRow("p6", image, "t2", reference=ok))[0].sum() > 0
    named = ManifestRow("p6", image, "t2", reference=gray, reference_labels=(50,))
    assert reference_mask(named)[0].sum() == (np.rint(img) == 50).sum()  # labels named: taken


def test_reference_without_requested_labels(thin, tmp_path):
    image, seg, *_ = thin
    row = ManifestRow("p7", image, "t2", reference=seg, reference_labels=(3, 4))
    with pytest.raises(InputError, match=r"patient p7: .*none of the requested labels 3,4 "
                       r"\(present: 1,2\)"):  # fmt: skip
        prepare_case(row, tmp_path)


def test_an_empty_reference_names_the_tumour_free_kind(thin, tmp_path):
    """An all-zero expert label (what an export writes for no tumour) is refused, pointing
    to the row's reference_kind tumor_free without a reference (a user audit: the error
    gave no way out), which scores the patient as tumour-free."""
    image, seg, img, lab, aff = thin
    empty = _write(tmp_path / "empty.nii.gz", np.zeros_like(lab), aff, "uint8")
    with pytest.raises(InputError, match=r"patient p8: the reference has no label > 0 .*"
                       r"reference_kind tumor_free and no reference\)$"):  # fmt: skip
        reference_mask(ManifestRow("p8", image, "t2", reference=empty))
    free = ManifestRow("p8", image, "t2", reference_kind="tumor_free")
    assert prepare_case(free, tmp_path).reference_kind == "tumor_free"


def test_reference_outside_the_image_world_space(thin, tmp_path):
    image, _, _, lab, aff = thin
    far = aff.copy()
    far[:3, 3] = [500.0, 0.0, 0.0]
    seg = _write(tmp_path / "far.nii.gz", lab, far, "uint8")
    with pytest.raises(InputError, match=r"patient p2: the reference does not overlap the image"):
        prepare_case(ManifestRow("p2", image, "t2", reference=seg), tmp_path)


def test_emulation_on_slices_already_thicker_than_the_step(tmp_path):
    img = np.random.default_rng(1).random((8, 8, 10)).astype(np.float32) + 1
    image = _write(tmp_path / "thick.nii.gz", img, np.diag([1.0, 1.0, 6.5, 1.0]))
    row = ManifestRow("p3", image, "t2", emulate_step_mm=5.0, emulate_thickness_mm=2.0)
    with pytest.raises(InputError, match=r"patient p3: emulate_step_mm = 5 mm is smaller than "
                       r"the image's own slice step 6.5 mm"):  # fmt: skip
        prepare_case(row, tmp_path / "emu")
    assert not (tmp_path / "emu" / "p3").exists()


def test_emulation_needs_nifti_and_no_overrides(thin, tmp_path):
    image, *_ = thin
    row = ManifestRow("p4", image, "t2", emulate_step_mm=5.0, slice_thickness_mm=2.0)
    with pytest.raises(InputError, match="cannot be combined with emulation"):
        prepare_case(row, tmp_path)


def test_brain_mask_is_emulated_like_the_image_onto_the_run_grid(thin, tmp_path):
    """Issue 7: slab = mean of its thin slices of (values > 0.5), brain where >= 0.5."""
    from tumor3d.storage.brain_mask import read_given_brain_mask
    from tumor3d.storage.readers import read_scan

    image, seg, _, _, aff = thin
    values = np.zeros((12, 10, 20), np.float32)
    for z in (0, 11, 12):
        values[2:10, 2:8, z] = 1.0
    values[2:10, 2:8, 15] = 0.9  # a probability map: brain
    values[2:10, 2:8, 16] = 0.05  # not brain (the mean of the values, 0.475, would drop it)
    values[0, 0, 5] = 0.4  # never brain
    mask = _write(tmp_path / "brain_prob.nii.gz", values, aff)
    row = ManifestRow(
        "p1", image, "t2", reference=seg, emulate_step_mm=5.0, emulate_thickness_mm=2.0,
        brain_mask=mask,
    )  # fmt: skip
    prep = prepare_case(row, tmp_path / "emu")
    emulated = prep.run_row.brain_mask
    assert emulated == (tmp_path / "emu" / "p1" / "p1_brain_mask.nii.gz").resolve()
    thick, thick_aff = nifti.read_nifti(prep.run_row.image)
    got, got_aff = nifti.read_nifti(emulated)
    assert got.shape == thick.shape == (12, 10, 4)
    np.testing.assert_array_equal(got_aff, thick_aff)
    brain = values > 0.5
    for j in range(4):  # 2 mm every 5 mm from 1 mm: thin slices 5j and 5j + 1
        expected = brain[:, :, [5 * j, 5 * j + 1]].mean(axis=2) >= 0.5
        np.testing.assert_array_equal(got[:, :, j] > 0, expected, err_msg=f"thick slice {j}")
    assert [bool(got[:, :, j].any()) for j in range(4)] == [True, False, True, True]
    # the run's image and mask agree as the cohort checks them
    scan = read_scan(prep.run_row.image, patient_id="p1")
    assert read_given_brain_mask(emulated, scan).mask.sum() == got.sum()
    # a native row keeps its own mask (checked by the cohort when the patient runs)
    native = prepare_case(ManifestRow("p1", image, "t2", brain_mask=mask), tmp_path / "n")
    assert native.run_row.brain_mask == mask


def test_bad_brain_mask_of_an_emulated_row_names_the_patient_and_the_file(thin, tmp_path):
    image, _, _, _, aff = thin
    short = _write(tmp_path / "short_mask.nii.gz", np.ones((12, 10, 19), np.float32), aff)
    row = ManifestRow("p9", image, "t2", emulate_step_mm=5.0, brain_mask=short)
    with pytest.raises(InputError, match=r"short_mask\.nii\.gz: patient p9: brain mask: shape "
                       r"\(12, 10, 19\) differs from the image's \(12, 10, 20\)"):  # fmt: skip
        prepare_case(row, tmp_path / "emu")
