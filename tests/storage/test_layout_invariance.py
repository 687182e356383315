"""The tumour found does not depend on how the file lays out its voxels.

A NIfTI file may store the same acquisition with its axes in any order and
direction (LPS from BraTS and DICOM converters, RAS from ``nibabel``'s
canonical form, the slice axis first from some exporters). The reader turns
each into the same ``(z, y, x)`` stack and affine, in the working orientation
(LPS for an axial stack), and the lesion model takes the left-right axis from
that affine for its symmetry rule. The mask found,
placed in the world by the reader's affine, must be the same voxels for
every layout; a patient whose anatomy is the mirror image (the data
flipped along left-right, the affine kept) must get the mirrored mask, so
that no rule prefers a side; and a bilateral pair of bright structures is no
tumour on FLAIR in any layout, which holds only if the symmetry rule mirrors
about the left-right axis the affine gives.
"""

from __future__ import annotations

from functools import cache

import nibabel as nib
import numpy as np
import pytest

from tumor3d.config import PipelineConfig
from tumor3d.imaging.affine import zyx_index_to_ras
from tumor3d.imaging.preprocess import preprocess_volume
from tumor3d.phantom import make_phantom_patient
from tumor3d.segmentation.detect import detect_abnormal_slices
from tumor3d.segmentation.lesion import left_right_axis
from tumor3d.segmentation.segment import segment_tumor
from tumor3d.storage.readers import read_scan

# 128 x 128 pixels of 1.875 mm (the default field of view), 16 slices: what is checked
# (the same voxels whatever the layout) does not depend on the image size; the bilateral
# pair below keeps the full size, where one 9 mm ball alone is found with > 300 voxels
SMALL = {"n_slices": 16, "matrix_size": (128, 128)}


def _reversed(affine, shape_xyz, axes):
    """``affine`` of the same voxels stored with the voxel ``axes`` reversed."""
    out = np.array(affine, dtype=float)
    for a in axes:
        out[:3, 3] += out[:3, a] * (shape_xyz[a] - 1)
        out[:3, a] *= -1.0
    return out


def _save(path, data_xyz, affine):
    nib.save(nib.Nifti1Image(np.ascontiguousarray(data_xyz), affine), str(path))
    return path


@cache
def _tumour_world_cmm(path, modality: str) -> frozenset[tuple[int, int, int]]:
    """The default pipeline's tumour voxels as RAS centres in 0.01 mm (a set).

    Kept per file: the module's files are written once, and the mirror test reads the
    "given" layout's tumour that the layout test found (not a second pipeline run)."""
    cfg = PipelineConfig()
    scan = read_scan(path, modality=modality)
    spacing = (scan.slice_step_mm, *scan.pixel_spacing_mm)
    lr = left_right_axis(scan.affine)
    pre = preprocess_volume(scan.image, **cfg.preprocess.model_dump(), spacing_mm=spacing)
    det = detect_abnormal_slices(
        pre.enhanced, pre.brain_mask, modality=modality, spacing_mm=spacing, lr_axis=lr,
        **cfg.detect.model_dump(),
    )  # fmt: skip
    seg = segment_tumor(
        pre.enhanced, pre.brain_mask, det, modality=modality, spacing_mm=spacing, lr_axis=lr,
        **cfg.segment.model_dump(),
    )  # fmt: skip
    ras = zyx_index_to_ras(np.argwhere(seg.tumor_mask), scan.affine)
    return frozenset(map(tuple, np.rint(ras * 100.0).astype(np.int64)))


@pytest.fixture(scope="module", params=["flair", "t2"])
def phantom_files(request, tmp_path_factory):
    """One phantom written in four layouts, and its mirror image; the modality."""
    modality = request.param
    tmp = tmp_path_factory.mktemp(f"layout-{modality}")
    patient = make_phantom_patient(0, modality=modality, **SMALL)
    data = patient.scan.image.transpose(2, 1, 0)  # (x, y, z): NIfTI's order
    aff = patient.scan.affine  # columns to the left, rows to posterior: LPS-like
    ras = nib.as_closest_canonical(nib.Nifti1Image(data, aff))
    assert nib.aff2axcodes(aff) != nib.aff2axcodes(ras.affine)  # a different layout
    files = {
        "given": _save(tmp / "given.nii.gz", data, aff),
        "ras": _save(tmp / "ras.nii.gz", np.asarray(ras.dataobj), ras.affine),
        "slices first": _save(tmp / "zxy.nii.gz", data.transpose(2, 0, 1), aff[:, [2, 0, 1, 3]]),
        "rows and columns swapped": _save(
            tmp / "yxz.nii.gz", data.transpose(1, 0, 2), aff[:, [1, 0, 2, 3]]
        ),
        "slices top down, rows to the front": _save(
            tmp / "lai.nii.gz", data[:, ::-1, ::-1], _reversed(aff, data.shape, (1, 2))
        ),
    }
    mirror = _save(tmp / "mirror.nii.gz", data[::-1], aff)  # x runs left-right: flip it
    return files, mirror, aff, data.shape[0], modality


def test_the_tumour_is_the_same_voxels_whatever_the_files_layout(phantom_files):
    # exact equality: the layouts only permute and flip the voxels, and the phantom's
    # affine is exact in binary, so the world centres are the same numbers; a change
    # that breaks a tie by raster order (e.g. the first of two equal components) would
    # show here, and is a layout dependence too
    files, _, _, _, modality = phantom_files
    found = {name: _tumour_world_cmm(path, modality) for name, path in files.items()}
    assert len(found["given"]) > 1000  # a tumour is found (1,730 voxels at this size)
    for name, voxels in found.items():
        assert voxels == found["given"], name


def test_a_file_storing_the_slices_in_any_order_or_direction_gives_the_same_stack(
    phantom_files,
):
    """RAS, rows and columns swapped, the slice axis first, slices from the top down with
    rows to the front: the same (z, y, x) array and affine, so no method sees the storage
    (the learned one reads positions and slices as images: a BraTS FLAIR stored LAS lost
    16 % of its learned volume); each file's own order comes back on output."""
    files, _, _, _, modality = phantom_files
    given = read_scan(files["given"], modality=modality)
    for name in files:
        scan = read_scan(files[name], modality=modality)
        np.testing.assert_array_equal(scan.image, given.image, err_msg=name)
        np.testing.assert_array_equal(scan.affine, given.affine, err_msg=name)
        stored = np.asarray(nib.load(files[name]).dataobj)
        np.testing.assert_array_equal(scan.source_grid.to_source(scan.image), stored)


def test_the_mirror_image_patient_gets_the_mirror_image_tumour(phantom_files):
    files, mirror, aff, nx, modality = phantom_files
    given = _tumour_world_cmm(files["given"], modality)
    # index i along x holds what index nx - 1 - i held: world x -> 2 c - x, with c the
    # world x of the grid's middle column (aff's x column is along R only)
    assert np.count_nonzero(aff[:3, 0]) == 1 and aff[0, 0] != 0.0
    two_c = int(round(100.0 * (2.0 * aff[0, 3] + aff[0, 0] * (nx - 1))))
    expected = {(two_c - x, y, z) for x, y, z in given}
    assert _tumour_world_cmm(mirror, modality) == expected


def _with_bilateral_pair(image_zyx, affine, gray: float) -> np.ndarray:
    """``image_zyx`` with two 9 mm balls at ``gray``, 30 mm either side of the midline.

    The phantom's head is centred on RAS (0, 0, 0); the balls lie posterior (y = -25
    mm), deep in the white matter, and are each other's left-right mirror image but
    not their own front-back one.
    """
    zyx = np.indices(image_zyx.shape).reshape(3, -1).T
    ras = zyx_index_to_ras(zyx, affine).reshape(*image_zyx.shape, 3)
    out = image_zyx.copy()
    for r_mm in (-30.0, 30.0):
        d2 = (ras[..., 0] - r_mm) ** 2 + (ras[..., 1] + 25.0) ** 2 + (ras[..., 2] - 5.0) ** 2
        out[d2 <= 9.0**2] = gray
    return out


def test_a_bilateral_pair_is_no_tumour_on_flair_in_any_layout(tmp_path):
    patient = make_phantom_patient(0, modality="flair", tumor=False)
    aff = patient.scan.affine
    tumour_gray = 850.0  # the FLAIR phantom's tumour (tumor3d.phantom.raster)
    data = _with_bilateral_pair(patient.scan.image, aff, tumour_gray).transpose(2, 1, 0)
    ras = nib.as_closest_canonical(nib.Nifti1Image(data, aff))
    layouts = {
        "given": _save(tmp_path / "given.nii.gz", data, aff),
        "ras": _save(tmp_path / "ras.nii.gz", np.asarray(ras.dataobj), ras.affine),
        "slices first": _save(
            tmp_path / "zxy.nii.gz", data.transpose(2, 0, 1), aff[:, [2, 0, 1, 3]]
        ),
        "rows and columns swapped": _save(
            tmp_path / "yxz.nii.gz", data.transpose(1, 0, 2), aff[:, [1, 0, 2, 3]]
        ),
    }
    for name, path in layouts.items():
        assert _tumour_world_cmm(path, "flair") == set(), name
    # the same pair with one ball only is a tumour: the pair is rejected for its mirror
    one = np.where(data[: data.shape[0] // 2] == tumour_gray)
    data_one = data.copy()
    data_one[: data.shape[0] // 2][one] = patient.scan.image.transpose(2, 1, 0)[
        : data.shape[0] // 2
    ][one]
    assert len(_tumour_world_cmm(_save(tmp_path / "one.nii.gz", data_one, aff), "flair")) > 300
