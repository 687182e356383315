"""NRRD and MetaImage input through SimpleITK: same geometry as NIfTI, LPS -> RAS (issue 12)."""

from __future__ import annotations

import nibabel as nib
import numpy as np
import pytest
import SimpleITK as sitk

from tumor3d.errors import InputError
from tumor3d.storage.readers import read_scan

SUFFIXES = [".nrrd", ".nhdr", ".mha", ".mhd"]


def rotation_lps(yaw_deg=20.0, pitch_deg=10.0):
    a, b = np.deg2rad(yaw_deg), np.deg2rad(pitch_deg)
    rz = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    rx = np.array([[1, 0, 0], [0, np.cos(b), -np.sin(b)], [0, np.sin(b), np.cos(b)]])
    return rz @ rx


def phantom_ijk(shape, seed=0):
    """A blob over random texture, in the file's voxel order (i, j, k)."""
    rng = np.random.default_rng(seed)
    ii, jj, kk = np.indices(shape)
    c = (np.array(shape) - 1) / 2
    blob = ((ii - c[0]) ** 2 + (jj - c[1]) ** 2 + ((kk - c[2]) * 3) ** 2) < (shape[0] / 3) ** 2
    return (rng.integers(10, 50, size=shape) + 200 * blob).astype(np.int16)


def write_itk(path, data_ijk, spacing, origin, direction):
    img = sitk.GetImageFromArray(np.ascontiguousarray(data_ijk.transpose(2, 1, 0)))  # (k, j, i)
    img.SetSpacing(tuple(float(s) for s in spacing))
    img.SetOrigin(tuple(float(o) for o in origin))
    img.SetDirection(tuple(float(d) for d in np.asarray(direction).ravel()))
    sitk.WriteImage(img, str(path))
    return img


@pytest.mark.parametrize("suffix", SUFFIXES)
def test_world_position_of_a_voxel_is_itks_lps_point_flipped(tmp_path, suffix):
    shape, spacing, origin = (14, 12, 5), (0.9, 0.8, 5.0), (-40.0, 25.0, 12.5)
    data = phantom_ijk(shape)
    f = tmp_path / f"case{suffix}"
    img = write_itk(f, data, spacing, origin, rotation_lps())
    scan = read_scan(f)
    assert scan.shape == (5, 12, 14)
    np.testing.assert_array_equal(scan.image, data.transpose(2, 1, 0).astype(np.float32))
    assert scan.slice_step_mm == pytest.approx(5.0)
    assert scan.pixel_spacing_mm == pytest.approx((0.8, 0.9))
    kind = "NRRD" if suffix in (".nrrd", ".nhdr") else "MetaImage"
    assert scan.source.startswith(f"{kind} file case{suffix}")
    assert scan.patient_id == "case"
    for i, j, k in [(0, 0, 0), (13, 0, 0), (0, 11, 0), (0, 0, 4), (7, 3, 2)]:
        lps = np.array(img.TransformIndexToPhysicalPoint((i, j, k)))  # ITK's own mapping
        expected_ras = lps * [-1.0, -1.0, 1.0]
        np.testing.assert_allclose(scan.index_to_ras([[k, j, i]])[0], expected_ras, atol=1e-4)


@pytest.mark.parametrize("suffix", [".nrrd", ".mha"])
def test_itk_and_nifti_of_the_same_volume_agree(tmp_path, suffix):
    """Slice axis first in the file: the same permutation and affine as the NIfTI reader."""
    shape, spacing, origin = (6, 13, 11), (5.0, 0.9, 0.8), (12.0, -30.0, 40.0)
    direction = rotation_lps(35.0, -15.0)[:, [2, 0, 1]]  # slice axis = voxel axis 0
    data = phantom_ijk(shape, seed=3)
    img = write_itk(tmp_path / f"a{suffix}", data, spacing, origin, direction)
    lps = np.eye(4)
    lps[:3, :3] = np.asarray(img.GetDirection()).reshape(3, 3) * np.asarray(img.GetSpacing())
    lps[:3, 3] = img.GetOrigin()
    ras = np.diag([-1.0, -1.0, 1.0, 1.0]) @ lps
    nii = nib.Nifti1Image(data, ras)
    nii.set_sform(ras, code=1)
    nii.set_qform(ras, code=1)
    nib.save(nii, str(tmp_path / "a.nii.gz"))

    a, b = read_scan(tmp_path / f"a{suffix}"), read_scan(tmp_path / "a.nii.gz")
    assert a.source_grid.axes == b.source_grid.axes == (1, 2, 0)
    np.testing.assert_array_equal(a.image, b.image)
    np.testing.assert_allclose(a.affine, b.affine, atol=1e-4)
    np.testing.assert_allclose(a.source_grid.affine, b.source_grid.affine, atol=1e-4)
    assert a.slice_step_mm == pytest.approx(b.slice_step_mm)
    # voxels come back in the file's own grid, voxel for voxel
    np.testing.assert_array_equal(a.source_grid.to_source(a.image), data.astype(np.float32))


def test_itk_declared_size_limit_and_unreadable_file(tmp_path):
    f = tmp_path / "v.nrrd"
    write_itk(f, phantom_ijk((8, 8, 3)), (1, 1, 5), (0, 0, 0), np.eye(3))
    with pytest.raises(InputError, match=r"v\.nrrd: the header declares 8 x 8 x 3 = 192 voxels"):
        read_scan(f, max_voxels=100)
    bad = tmp_path / "bad.mha"
    bad.write_bytes(b"\x00\x01garbage")
    with pytest.raises(InputError, match=r"bad\.mha: not a readable MetaImage image") as info:
        read_scan(bad)
    assert "\n" not in str(info.value)


def test_itk_vector_and_2d_images_are_refused(tmp_path):
    rgb = sitk.GetImageFromArray(np.zeros((3, 8, 8, 3), np.uint8), isVector=True)
    sitk.WriteImage(rgb, str(tmp_path / "rgb.nrrd"))
    with pytest.raises(InputError, match="3-component"):
        read_scan(tmp_path / "rgb.nrrd")
    flat = sitk.GetImageFromArray(np.arange(64, dtype=np.int16).reshape(8, 8))
    sitk.WriteImage(flat, str(tmp_path / "flat.mha"))
    with pytest.raises(InputError, match="2-D image"):
        read_scan(tmp_path / "flat.mha")


@pytest.mark.parametrize("suffix", [".nhdr", ".mhd"])
def test_input_digest_of_a_detached_header_covers_its_data_file(tmp_path, suffix):
    from tumor3d.storage.inputs import input_digest

    f = tmp_path / f"v{suffix}"
    data = phantom_ijk((8, 8, 3))
    write_itk(f, data, (1, 1, 5), (0, 0, 0), np.eye(3))
    data_files = [p for p in tmp_path.iterdir() if p != f]
    assert len(data_files) == 1  # SimpleITK wrote the voxels beside the header
    d0 = input_digest(f)
    write_itk(f, data + 1, (1, 1, 5), (0, 0, 0), np.eye(3))  # same header, other voxels
    assert input_digest(f) != d0


def test_itk_4d_image_with_one_volume_is_read_as_3d(tmp_path):
    data = np.random.default_rng(0).integers(1, 100, (1, 3, 8, 8)).astype(np.int16)  # (t, k, j, i)
    sitk.WriteImage(sitk.GetImageFromArray(data, isVector=False), str(tmp_path / "four.nrrd"))
    scan = read_scan(tmp_path / "four.nrrd")
    assert scan.shape == (3, 8, 8)
    np.testing.assert_array_equal(scan.image, data[0].astype(np.float32))
