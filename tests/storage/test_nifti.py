"""Tests of tumor3d.storage.nifti: deterministic encoding and writing back on the source grid."""

from __future__ import annotations

import gzip

import nibabel as nib
import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.storage.nifti import (
    decode_nifti,
    encode_nifti,
    mask_to_source_nifti_bytes,
    read_nifti,
    volume_to_source_nifti_bytes,
)
from tumor3d.storage.readers import read_scan

OBLIQUE = np.array(
    [
        [-0.8660254, 0.0, 0.5 * 3.0, 12.25],
        [0.0, 0.75, 0.0, -30.5],
        [0.5, 0.0, 0.8660254 * 3.0, 7.0],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


@pytest.mark.parametrize("dtype", [np.uint8, np.int16, np.float32])
def test_round_trip_keeps_data_and_affine(tmp_path, dtype):
    rng = np.random.default_rng(0)
    data = rng.integers(0, 200, size=(7, 5, 4)).astype(dtype)
    if dtype == np.float32:
        data = data * np.float32(0.37)
    blob = encode_nifti(data, OBLIQUE, dtype=dtype)
    array, affine = decode_nifti(blob)
    assert array.dtype == np.dtype(dtype)
    np.testing.assert_array_equal(array, data)
    np.testing.assert_allclose(affine, OBLIQUE, rtol=0, atol=1e-6)  # float32 header fields
    # also through a file, and the header codes/units are as promised
    f = tmp_path / "x.nii.gz"
    f.write_bytes(blob)
    array2, affine2 = read_nifti(f)
    np.testing.assert_array_equal(array2, data)
    np.testing.assert_array_equal(affine2, affine)
    hdr = nib.load(str(f)).header
    assert int(hdr["sform_code"]) == 1 and int(hdr["qform_code"]) == 1
    assert hdr.get_xyzt_units()[0] == "mm"
    np.testing.assert_allclose(hdr.get_qform(), OBLIQUE, atol=1e-5)


def test_encoding_is_deterministic_and_gzip_has_no_timestamp():
    data = np.arange(60, dtype=np.int16).reshape(5, 4, 3)
    a = encode_nifti(data, OBLIQUE, dtype=np.int16)
    b = encode_nifti(data.copy(), OBLIQUE.copy(), dtype="int16")
    assert a == b
    assert a[:2] == b"\x1f\x8b" and a[4:8] == b"\x00\x00\x00\x00"  # gzip MTIME = 0
    c = encode_nifti(data + 1, OBLIQUE, dtype=np.int16)
    assert c != a
    assert len(gzip.decompress(a)) == 352 + data.nbytes


def test_encode_does_not_modify_input():
    data = np.linspace(0, 1, 24, dtype=np.float64).reshape(2, 3, 4)
    before = data.copy()
    encode_nifti(data, OBLIQUE, dtype=np.float32)
    np.testing.assert_array_equal(data, before)


@pytest.mark.parametrize(
    ("data", "dtype", "match"),
    [
        (np.zeros((2, 2, 2)), np.float64, r"dtype must be one of"),
        (np.zeros((2, 2)), np.uint8, r"array must be 3-D"),
        (np.full((2, 2, 2), 0.5), np.uint8, r"fractional part"),
        (np.full((2, 2, 2), 300), np.uint8, r"do not fit uint8"),
        (np.full((2, 2, 2), np.nan), np.int16, r"non-finite"),
    ],
)
def test_encode_rejects_bad_input(data, dtype, match):
    with pytest.raises(ValueError, match=match):
        encode_nifti(data, OBLIQUE, dtype=dtype)


def test_encode_rejects_singular_affine():
    with pytest.raises(ValueError, match=r"affine is singular"):
        encode_nifti(np.zeros((2, 2, 2)), np.diag([1.0, 0.0, 1.0, 1.0]), dtype=np.uint8)


def test_decode_rejects_garbage():
    with pytest.raises(InputError, match=r"not NIfTI-1 data"):
        decode_nifti(b"definitely not a nifti file")


def test_read_nifti_missing_file(tmp_path):
    with pytest.raises(InputError, match=r"missing\.nii\.gz: no such file"):
        read_nifti(tmp_path / "missing.nii.gz")


def _save(path, data, affine):
    img = nib.Nifti1Image(data, affine)
    img.set_sform(affine, code=1)
    img.set_qform(affine, code=1)
    nib.save(img, str(path))


LAS = np.array([[-0.9, 0, 0, 91.5], [0, 0.85, 0, -120.25], [0, 0, 5.0, -40.0], [0, 0, 0, 1.0]])
# slice axis first: source axis 0 runs superior at 4 mm, axes 1 and 2 are in-plane
PERMUTED = np.array([[0, -0.9, 0, 91.5], [0, 0, 0.85, -120.25], [4.0, 0, 0, -40.0], [0, 0, 0, 1.0]])


@pytest.mark.parametrize(
    ("affine", "shape", "axes"),
    [(LAS, (14, 11, 6), (0, 1, 2)), (PERMUTED, (6, 14, 11), (1, 2, 0))],
)
def test_mask_overlays_the_input_voxel_for_voxel(tmp_path, affine, shape, axes):
    rng = np.random.default_rng(7)
    source = rng.integers(0, 1000, size=shape).astype(np.int16)
    f = tmp_path / "input.nii.gz"
    _save(f, source, affine)
    scan = read_scan(f)
    assert scan.source_grid.axes == axes
    mask = scan.image > 600  # a "segmentation" on the Scan grid
    out = tmp_path / "mask.nii.gz"
    out.write_bytes(mask_to_source_nifti_bytes(mask, scan.source_grid))
    written = nib.load(str(out))
    original = nib.load(str(f))
    assert written.shape == original.shape
    np.testing.assert_array_equal(written.affine, original.affine)
    assert written.get_data_dtype() == np.uint8
    np.testing.assert_array_equal(np.asarray(written.dataobj), (source > 600).astype(np.uint8))


def test_mask_of_wrong_shape_rejected(tmp_path):
    f = tmp_path / "input.nii.gz"
    _save(f, np.arange(60, dtype=np.int16).reshape(5, 4, 3), LAS)
    scan = read_scan(f)
    with pytest.raises(ValueError, match=r"does not match the source grid"):
        mask_to_source_nifti_bytes(np.zeros((3, 4, 4), bool), scan.source_grid)


def test_fine_volume_written_on_its_own_grid_keeps_world_positions(tmp_path):
    f = tmp_path / "input.nii.gz"
    _save(f, np.arange(6 * 14 * 11, dtype=np.int16).reshape(6, 14, 11), PERMUTED)
    scan = read_scan(f)
    # a volume with 4x finer slices on the Scan's world space (z step / 4)
    fine_affine = np.array(scan.affine)
    fine_affine[:3, 2] /= 4
    rng = np.random.default_rng(3)
    fine = rng.integers(0, 2, size=(21, *scan.shape[1:])).astype(np.uint8)  # (z, y, x)
    blob = volume_to_source_nifti_bytes(fine, fine_affine, scan.source_grid, dtype=np.uint8)
    array, affine = decode_nifti(blob)
    # every fine voxel is written at its own world position, on a grid in the file's
    # axis order (the slice axis where the file has it)
    assert array.shape == tuple(np.array(fine.shape[::-1])[np.argsort(scan.source_grid.axes)])
    for z, y, x in rng.integers(0, [21, fine.shape[1], fine.shape[2]], size=(25, 3)):
        world_fine = fine_affine @ np.array([x, y, z, 1.0])
        src = np.linalg.solve(affine, world_fine)[:3]
        src_index = np.rint(src).astype(int)
        np.testing.assert_allclose(src, src_index, atol=1e-4)
        assert array[tuple(src_index)] == fine[z, y, x]


def test_masks_say_they_are_labels_and_a_probability_map_does_not(tmp_path):
    """NIFTI_INTENT_LABEL (1002) on the masks, as viewers that read intents expect."""
    f = tmp_path / "input.nii.gz"
    _save(f, np.arange(60, dtype=np.int16).reshape(5, 4, 3), LAS)
    scan = read_scan(f)
    mask = np.zeros(scan.shape, np.uint8)

    def intent(blob: bytes) -> str:
        return nib.Nifti1Image.from_bytes(gzip.decompress(blob)).header.get_intent()[0]

    grid = scan.source_grid
    assert intent(mask_to_source_nifti_bytes(mask, grid)) == "label"
    assert intent(volume_to_source_nifti_bytes(mask, scan.affine, grid, dtype="uint8")) == "label"
    prob = volume_to_source_nifti_bytes(mask, scan.affine, grid, dtype="float32")
    assert intent(prob) == "none"


def test_a_stored_probability_is_rounded_to_1_255_keeps_the_side_of_a_half_and_compresses():
    """The learned method's map is stored and published to 1/255 (``probability_for_storage``):
    within 1/510 of the model's values, on the 0.5 side they were, and a map whose
    background differs in its last bits (as a model's does) compresses as a smooth one."""
    from tumor3d.storage.nifti import probability_for_storage

    rng = np.random.default_rng(3)
    z, y, x = np.mgrid[0:12, 0:64, 0:64]
    blob = np.exp(-((y - 32.0) ** 2 + (x - 30.0) ** 2 + (4 * (z - 6.0)) ** 2) / 200.0)
    prob = np.clip(blob + rng.uniform(1e-6, 1e-4, blob.shape), 0, 1).astype(np.float32)
    prob[0, 0, :4] = [0.5, np.nextafter(np.float32(0.5), np.float32(0)), 1.0, 0.0]
    stored = probability_for_storage(prob)
    assert stored.dtype == np.float32 and stored.shape == prob.shape
    assert np.abs(stored.astype(np.float64) - prob).max() <= 0.5 / 255 + 1e-7
    levels = stored.astype(np.float64) * 255
    np.testing.assert_allclose(levels, np.round(levels), atol=1e-4)  # multiples of 1/255
    np.testing.assert_array_equal(stored >= 0.5, prob >= 0.5)  # no voxel changes side
    sizes = [len(encode_nifti(a, OBLIQUE, dtype=np.float32)) for a in (prob, stored)]
    # noise in the last bits does not compress (the rounded map: 7x smaller with ISA-L's
    # level 1, 14x with zlib's level 6)
    assert sizes[1] * 5 < sizes[0], sizes
    array, _ = decode_nifti(encode_nifti(stored, OBLIQUE, dtype=np.float32))
    np.testing.assert_array_equal(array, stored)


@pytest.mark.parametrize(
    ("codes", "qform_moved"),
    [((0, 0), False), ((2, 0), False), ((0, 1), False), ((1, 2), False), ((4, 4), False),
     ((2, 1), True), ((4, 2), True), ((1, 2), True)],
)  # fmt: skip
def test_outputs_are_placed_where_itk_places_the_input_whatever_its_header_codes(
    tmp_path, codes, qform_moved
):
    """3D Slicer and ITK-SNAP read NIfTI through ITK. A mask or map on the input's grid
    is placed by ITK (SimpleITK: origin, direction, spacing) and by nibabel exactly where
    they place the input, and keeps the input's sform and qform codes; a finer
    interpolated volume's voxel on an acquired slice lies on that slice's voxel (by ITK
    only when the input states its orientation). For codes 0 ITK places the input at the
    origin along L, P, S, nibabel centred along L, A, S: a mask written with codes 1 and
    nibabel's guess landed up to 176 mm away in ITK. A qform that differs from the sform
    (``qform_moved``: turned 5 degrees and shifted, as a registration tool writes the
    sform beside the scanner's qform) is what ITK reads unless the sform code is 1: the
    outputs carry it, mapped onto their own grid (written as the sform, they sat 5 mm off
    in ITK)."""
    sitk = pytest.importorskip("SimpleITK")
    rng = np.random.default_rng(5)
    source = rng.integers(0, 1000, size=(9, 8, 5)).astype(np.int16)
    affine = np.array([[-1.5, 0, 0, 40.0], [0, 2.0, 0, -60.0], [0, 0, 5.0, -20.0], [0, 0, 0, 1]])
    img = nib.Nifti1Image(source, affine)
    img.set_sform(affine, code=codes[0])
    turn = np.radians(5.0)
    moved = np.array(
        [[np.cos(turn), -np.sin(turn), 0, 5.0], [np.sin(turn), np.cos(turn), 0, -3.0],
         [0, 0, 1, 2.0], [0, 0, 0, 1]]
    ) @ affine  # fmt: skip
    img.set_qform(moved if qform_moved else affine, code=codes[1])
    img.header.set_zooms((1.5, 2.0, 5.0))
    f = tmp_path / "input.nii.gz"
    nib.save(img, f)
    scan = read_scan(f)
    assert scan.orientation_stated == any(codes)
    out = tmp_path / "mask.nii.gz"
    out.write_bytes(mask_to_source_nifti_bytes(scan.image > 600, scan.source_grid))
    written = nib.load(str(out))
    assert (int(written.header["sform_code"]), int(written.header["qform_code"])) == codes
    np.testing.assert_array_equal(np.asarray(written.dataobj), (source > 600).astype(np.uint8))
    # a probability map on the input grid alike
    prob = tmp_path / "prob.nii.gz"
    prob.write_bytes(
        volume_to_source_nifti_bytes(
            scan.image / 1000, scan.affine, scan.source_grid, dtype="float32"
        )
    )
    for written in (out, prob):  # nibabel, which places codes 0 otherwise, alike
        np.testing.assert_allclose(nib.load(str(written)).affine, img.affine, atol=1e-5)
    a = sitk.ReadImage(str(f))
    for b in (sitk.ReadImage(str(out)), sitk.ReadImage(str(prob))):
        np.testing.assert_allclose(b.GetOrigin(), a.GetOrigin(), atol=1e-4)
        np.testing.assert_allclose(b.GetDirection(), a.GetDirection(), atol=1e-6)
        np.testing.assert_allclose(b.GetSpacing(), a.GetSpacing(), atol=1e-6)
    # a volume 4x finer along the slices, on the scan's world space
    fine_affine = np.array(scan.affine)
    fine_affine[:3, 2] /= 4
    fine = np.zeros((4 * (scan.shape[0] - 1) + 1, *scan.shape[1:]), np.uint8)
    fout = tmp_path / "fine.nii.gz"
    fout.write_bytes(
        volume_to_source_nifti_bytes(fine, fine_affine, scan.source_grid, dtype="uint8")
    )
    c, fine_nib = sitk.ReadImage(str(fout)), nib.load(str(fout)).affine
    for z, y, x in [(0, 0, 0), (4, 6, 3), (3, 7, 1)]:  # (z, y, x) of the scan, acquired slice z
        src = scan.source_grid.to_source(_one_hot(scan.shape, (z, y, x)))
        i = np.argwhere(src)[0]
        fsrc, _ = scan.source_grid.to_source_with_affine(
            _one_hot(fine.shape, (4 * z, y, x)), fine_affine
        )
        j = np.argwhere(fsrc)[0]
        np.testing.assert_allclose(
            (fine_nib @ [*j, 1])[:3], (img.affine @ [*i, 1])[:3], atol=1e-3
        )  # by nibabel
        if any(codes):  # by ITK too (codes 0: ITK's placement is not nibabel's guess)
            np.testing.assert_allclose(
                c.TransformIndexToPhysicalPoint([int(v) for v in j]),
                a.TransformIndexToPhysicalPoint([int(v) for v in i]),
                atol=1e-3,
            )


def _one_hot(shape, at):
    arr = np.zeros(shape, np.uint8)
    arr[at] = 1
    return arr
