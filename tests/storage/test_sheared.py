"""Sheared grids: Eq. 7 and voxel volumes use the distance between slice planes (issue 12)."""

from __future__ import annotations

import nibabel as nib
import numpy as np
import pydicom
import pytest
from dicom_factory import write_series

from tumor3d.errors import InputError
from tumor3d.imaging.affine import slab_height_mm, slice_plane_spacing_mm
from tumor3d.imaging.scan import Scan, SourceGrid
from tumor3d.metrics import volume_eq7_mm3, volume_voxel_mm3, voxel_volume_mm3
from tumor3d.storage.readers import read_scan

# 1 mm pixels, 5 mm between slice planes, the slice axis tilted by 3 mm per slice in x
SHEARED = np.array(
    [
        [1.0, 0.0, 3.0, -30.0],
        [0.0, 1.0, 0.0, -30.0],
        [0.0, 0.0, 5.0, -40.0],
        [0.0, 0.0, 0.0, 1.0],
    ]
)


def ball_phantom(affine, shape=(64, 64, 17), center=(26.0, 2.0, 0.0), radius=22.0):
    """A ball of ``radius`` mm rasterised at the voxel centres of a (possibly sheared) grid."""
    ijk = np.indices(shape).reshape(3, -1).T.astype(float)
    world = ijk @ affine[:3, :3].T + affine[:3, 3]
    inside = np.linalg.norm(world - np.asarray(center), axis=1) <= radius
    return inside.reshape(shape)


def write(path, data, affine):
    img = nib.Nifti1Image(np.asarray(data, np.int16), affine)
    img.set_sform(affine, code=1)
    img.set_qform(affine, code=1)
    nib.save(img, str(path))
    return path


def test_plane_spacing_is_the_column_projected_on_the_slice_normal():
    normal = np.cross(SHEARED[:3, 0], SHEARED[:3, 1])
    normal /= np.linalg.norm(normal)
    expected = abs(SHEARED[:3, 2] @ normal)  # independent: projection on the normal
    assert expected == pytest.approx(5.0)
    assert slice_plane_spacing_mm(SHEARED) == pytest.approx(expected)
    assert np.linalg.norm(SHEARED[:3, 2]) == pytest.approx(np.sqrt(34.0))  # 5.83, not the step


def test_sheared_nifti_gives_eq7_and_voxel_volume_of_the_mask(tmp_path):
    mask = ball_phantom(SHEARED)
    n = int(mask.sum())
    assert n > 1000
    f = write(tmp_path / "sheared.nii.gz", 10 + 90 * mask, SHEARED)
    scan = read_scan(f)
    truth = n * abs(np.linalg.det(SHEARED[:3, :3]))  # the mask's own volume: n voxels of |det|

    assert scan.slice_step_mm == pytest.approx(5.0)
    assert scan.slab_height_mm == pytest.approx(5.0)
    assert "sheared grid" in scan.source
    tumor = scan.image > 50  # (z, y, x)
    per_slice = tumor.reshape(tumor.shape[0], -1).sum(axis=1)
    eq7 = volume_eq7_mm3(
        per_slice,
        per_slice > 0,
        pixel_area_mm2=scan.pixel_area_mm2,
        slab_height_mm=slab_height_mm(
            scan.slice_step_mm, scan.slice_thickness_mm, scan.slice_gap_mm
        ),
    )
    voxel = volume_voxel_mm3(tumor, voxel_volume_mm3=voxel_volume_mm3(scan.affine))
    assert eq7 == pytest.approx(truth, rel=1e-9)
    assert voxel == pytest.approx(truth, rel=1e-9)
    assert scan.voxel_volume_mm3 == pytest.approx(5.0)
    # and the ball is where the affine puts it: its analytic volume within rasterisation error
    assert truth == pytest.approx(4.0 / 3.0 * np.pi * 22.0**3, rel=0.05)


def test_sheared_nifti_with_a_stated_gap_keeps_slab_height_at_the_plane_spacing(tmp_path):
    f = write(tmp_path / "sheared.nii.gz", 10 + 90 * ball_phantom(SHEARED), SHEARED)
    scan = read_scan(f, slice_thickness_mm=2.0)
    assert (scan.slice_thickness_mm, scan.slice_gap_mm) == pytest.approx((2.0, 3.0))
    assert scan.slab_height_mm == pytest.approx(5.0)


def test_in_plane_shear_is_refused_naming_the_file(tmp_path):
    affine = SHEARED.copy()
    affine[0, 1] = 0.3  # x and y columns 73 degrees apart
    f = write(tmp_path / "skew.nii.gz", 10 + 90 * ball_phantom(affine), affine)
    with pytest.raises(InputError, match=r"skew\.nii\.gz: the in-plane voxel axes .* not perp"):
        read_scan(f)


def test_scan_refuses_a_slice_step_that_is_the_column_length():
    grid = SourceGrid(shape=(4, 3, 2), affine=SHEARED)
    kw = dict(
        image=np.arange(24, dtype=np.float32).reshape(2, 3, 4),
        affine=SHEARED,
        pixel_spacing_mm=(1.0, 1.0),
        slice_thickness_mm=2.0,
        slice_gap_mm=None,
        modality="t2",
        patient_id="p",
        source="test",
        source_grid=grid,
    )
    with pytest.raises(InputError, match="slice step 5.83095 mm disagrees"):
        Scan(slice_step_mm=float(np.linalg.norm(SHEARED[:3, 2])), **kw)
    assert Scan(slice_step_mm=5.0, **kw).slab_height_mm == 5.0


def test_gantry_tilted_dicom_keeps_its_geometry_and_plane_spacing(tmp_path):
    s = write_series(tmp_path / "tilt", n_slices=6, step_mm=5.0, tilt_mm_per_slice=1.5)
    scan = read_scan(tmp_path / "tilt")
    assert scan.slice_step_mm == pytest.approx(5.0, abs=1e-5)  # between planes, not 5.22
    assert "gantry tilt: slice planes 5 mm apart" in scan.source
    # every voxel where DICOM PS3.3 C.7.6.2.1.1 puts it (LPS -> RAS)
    dy, dx = s.pixel_spacing
    for k, j, i in [(0, 0, 0), (5, 0, 0), (3, 7, 5), (5, 15, 11)]:
        lps = s.positions[k] + i * dx * s.row_dir + j * dy * s.col_dir
        np.testing.assert_allclose(
            scan.index_to_ras([[k, j, i]])[0], lps * [-1.0, -1.0, 1.0], atol=1e-4
        )
    assert scan.voxel_volume_mm3 == pytest.approx(dx * dy * 5.0, rel=1e-6)


def test_irregularly_drifting_dicom_is_refused(tmp_path):
    rng = np.random.default_rng(0)
    write_series(tmp_path / "wobble", n_slices=6, tilt_mm_per_slice=0.0)
    # move one middle slice sideways by 2 mm: not a straight line any more
    f = sorted((tmp_path / "wobble").glob("*.dcm"))[int(rng.integers(1, 5))]
    ds = pydicom.dcmread(f)
    pos = [float(v) for v in ds.ImagePositionPatient]
    iop = [float(v) for v in ds.ImageOrientationPatient]
    ds.ImagePositionPatient = [f"{p + 2.0 * c:.6f}" for p, c in zip(pos, iop[3:], strict=True)]
    ds.save_as(f)
    with pytest.raises(InputError, match="not along a straight line"):
        read_scan(tmp_path / "wobble")
