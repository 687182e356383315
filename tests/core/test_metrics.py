"""Tests of tumor3d.metrics: Eq. 7-8 volume, voxel volume, Eq. 9 error."""

from __future__ import annotations

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.metrics import (
    mm3_to_ml,
    relative_error_percent,
    volume_eq7_mm3,
    volume_voxel_mm3,
    voxel_volume_mm3,
)


def test_eq7_hand_computed():
    counts = np.array([0, 120, 250, 80, 0])
    abnormal = np.array([False, True, True, True, False])
    # (2 mm thickness + 3 mm gap) * (120 + 250 + 80) px * (0.5 mm * 0.6 mm)
    expected = 5.0 * 450 * 0.3
    got = volume_eq7_mm3(counts, abnormal, pixel_area_mm2=0.5 * 0.6, slab_height_mm=2.0 + 3.0)
    assert got == pytest.approx(expected, rel=1e-12)


def test_eq7_counts_only_abnormal_slices():
    counts = np.array([1000, 10, 20, 5000])
    abnormal = np.array([False, True, True, False])
    got = volume_eq7_mm3(counts, abnormal, pixel_area_mm2=1.0, slab_height_mm=5.0)
    assert got == pytest.approx(5.0 * 30)
    none = volume_eq7_mm3(counts, np.zeros(4, bool), pixel_area_mm2=1.0, slab_height_mm=5.0)
    assert none == 0.0


def test_eq7_from_mask_counts_and_integral_floats():
    mask = np.zeros((3, 4, 4), dtype=bool)
    mask[1, :2, :3] = True  # 6 pixels
    mask[2, 0, 0] = True  # 1 pixel
    counts = mask.sum(axis=(1, 2))
    abnormal = np.array([False, True, True])
    got = volume_eq7_mm3(counts, abnormal, pixel_area_mm2=0.25, slab_height_mm=4.0)
    assert got == pytest.approx(4.0 * 7 * 0.25)
    got_f = volume_eq7_mm3(counts.astype(float), abnormal, pixel_area_mm2=0.25, slab_height_mm=4.0)
    assert got_f == got


def test_eq7_inputs_not_modified():
    counts = np.array([3, 4])
    flags = np.array([True, False])
    volume_eq7_mm3(counts, flags, pixel_area_mm2=1.0, slab_height_mm=1.0)
    np.testing.assert_array_equal(counts, [3, 4])
    np.testing.assert_array_equal(flags, [True, False])


_C = np.array([1, 2, 3])
_A = np.array([True, True, False])


@pytest.mark.parametrize(
    ("counts", "abnormal", "kwargs", "match"),
    [
        (np.ones((2, 2), int), np.ones((2, 2), bool), {}, "1-D"),
        (_C, _A[:2], {}, "shape of tumor_pixels"),
        (np.array([1.5, 2.0, 3.0]), _A, {}, "whole pixel counts"),
        (np.array([1, -2, 3]), _A, {}, ">= 0"),
        (_C, np.array([1, 1, 0]), {}, "boolean"),
        (_C, _A, {"pixel_area_mm2": 0.0}, "pixel_area_mm2 must be a positive"),
        (_C, _A, {"pixel_area_mm2": "1"}, "pixel_area_mm2 must be a number"),
        (_C, _A, {"slab_height_mm": float("inf")}, "slab_height_mm must be a positive"),
    ],
)
def test_eq7_validation(counts, abnormal, kwargs, match):
    params = {"pixel_area_mm2": 1.0, "slab_height_mm": 5.0, **kwargs}
    with pytest.raises(InputError, match=match):
        volume_eq7_mm3(counts, abnormal, **params)


def test_voxel_volume_of_anisotropic_rotated_affine():
    theta = 0.3
    rot = np.array(
        [[np.cos(theta), -np.sin(theta), 0], [np.sin(theta), np.cos(theta), 0], [0, 0, 1]]
    )
    aff = np.eye(4)
    aff[:3, :3] = rot @ np.diag([0.9, 0.8, 2.0])
    aff[:3, 3] = [10, -20, 30]
    assert voxel_volume_mm3(aff) == pytest.approx(0.9 * 0.8 * 2.0, rel=1e-12)
    flipped = aff.copy()
    flipped[:3, 0] *= -1  # negative determinant
    assert voxel_volume_mm3(flipped) == pytest.approx(1.44, rel=1e-12)


@pytest.mark.parametrize(
    ("affine", "match"),
    [
        (np.eye(3), "4x4"),
        (np.diag([1.0, np.inf, 1.0, 1.0]), "finite"),
        (np.diag([1.0, 0.0, 1.0, 1.0]), "singular"),
    ],
)
def test_voxel_volume_validation(affine, match):
    with pytest.raises(InputError, match=match):
        voxel_volume_mm3(affine)


def test_volume_voxel_counts_voxels():
    mask = np.zeros((4, 5, 6), dtype=np.uint8)
    mask[1:3, 1:4, 2:6] = 1  # 2 * 3 * 4 = 24 voxels
    assert volume_voxel_mm3(mask, voxel_volume_mm3=1.5) == pytest.approx(36.0)
    assert volume_voxel_mm3(mask.astype(bool), voxel_volume_mm3=1.5) == pytest.approx(36.0)


@pytest.mark.parametrize(
    ("mask", "vv", "match"),
    [
        (np.ones(3, float), 1.0, "bool or integer"),
        (np.array([0, 2]), 1.0, "only 0 and 1"),
        (np.ones(3, bool), -1.0, "voxel_volume_mm3 must be a positive"),
    ],
)
def test_volume_voxel_validation(mask, vv, match):
    with pytest.raises(InputError, match=match):
        volume_voxel_mm3(mask, voxel_volume_mm3=vv)


def test_relative_error_matches_table3_rows():
    # Table 3 of the paper, truncated to 2 decimals: 3841/3785 -> 1.47, 1764/1805 -> 2.27
    assert int(relative_error_percent(3841, 3785) * 100) / 100 == 1.47
    assert int(relative_error_percent(1764, 1805) * 100) / 100 == 2.27
    assert relative_error_percent(90.0, 100.0) == pytest.approx(10.0)
    assert relative_error_percent(110.0, 100.0) == pytest.approx(10.0)
    assert relative_error_percent(100.0, 100.0) == 0.0


@pytest.mark.parametrize(
    ("est", "truth", "match"),
    [
        (1.0, 0.0, "truth must be a positive"),
        (1.0, -3.0, "truth must be a positive"),
        (float("nan"), 1.0, "estimate must be finite"),
        (None, 1.0, "estimate must be a number"),
    ],
)
def test_relative_error_validation(est, truth, match):
    with pytest.raises(InputError, match=match):
        relative_error_percent(est, truth)


def test_mm3_to_ml():
    assert mm3_to_ml(215.26) == pytest.approx(0.21526)
    assert mm3_to_ml(0.0) == 0.0
    with pytest.raises(InputError, match="volume_mm3 must be finite"):
        mm3_to_ml(float("inf"))


# -- measure_volumes: the measure stage's rules -------------------------------


def _cube_mesh(side: float):
    """A closed, outward cube of edge ``side`` mm (volume side**3)."""
    from tumor3d.geometry.mesh import Mesh

    v = np.array([[x, y, z] for x in (0, side) for y in (0, side) for z in (0, side)], float)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = [f for a, b, c, d in quads for f in ((a, b, c), (a, c, d))]
    return Mesh(v, np.array(faces))


def test_measure_volumes_slice_rules():
    from tumor3d.metrics import measure_volumes

    counts = np.array([1, 10, 20, 4, 0])  # an unflagged slice of one tumour pixel counts too
    flags = np.array([False, True, True, False, True])
    fine = np.zeros((4, 2, 2), bool)
    fine[1:3, :, :1] = True  # 4 voxels
    kw = dict(pixel_area_mm2=0.5, slab_height_mm=5.0)
    seg = measure_volumes(counts, flags, fine, np.diag([1.0, 1.0, 2.0, 1.0]), **kw)
    lit = measure_volumes(
        counts, flags, fine, np.diag([1.0, 1.0, 2.0, 1.0]), eq7_slices="abnormal", **kw
    )
    # independent: the segmented rule counts every tumour pixel, the literal only flagged ones
    assert seg.volume_eq7_mm3 == pytest.approx(5.0 * 0.5 * (1 + 10 + 20 + 4))
    assert lit.volume_eq7_mm3 == pytest.approx(5.0 * 0.5 * (10 + 20))
    assert (seg.n_eq7_slices, lit.n_eq7_slices) == (5, 3)
    assert (seg.n_abnormal_slices, seg.n_tumor_slices, seg.n_slices) == (3, 4, 5)
    assert seg.volume_voxel_mm3 == pytest.approx(4 * 2.0)
    assert seg.volume_mesh_mm3 == seg.volume_mesh_simplified_mm3 == 0.0
    row = seg.to_row()
    assert row["volume_eq7_ml"] == pytest.approx(row["volume_eq7_mm3"] / 1000)
    assert row["eq7_slice_rule"] == "segmented"


def test_measure_volumes_meshes_and_validation():
    from tumor3d.metrics import measure_volumes
    from tumor3d.pipeline import empty_mesh

    one = np.zeros((1, 1, 1), bool)
    m = measure_volumes([0], [False], one, np.eye(4), pixel_area_mm2=1.0, slab_height_mm=1.0,
                        mesh=_cube_mesh(3.0), mesh_simplified=empty_mesh())  # fmt: skip
    assert m.volume_mesh_mm3 == pytest.approx(27.0)
    assert m.volume_mesh_simplified_mm3 == 0.0
    with pytest.raises(InputError, match="eq7_slices"):
        measure_volumes([0], [False], one, np.eye(4), pixel_area_mm2=1.0, slab_height_mm=1.0,
                        eq7_slices="all")  # fmt: skip
    with pytest.raises(InputError, match="boolean"):
        measure_volumes([0], [0], one, np.eye(4), pixel_area_mm2=1.0, slab_height_mm=1.0)
    with pytest.raises(TypeError, match="Mesh"):
        measure_volumes([0], [False], one, np.eye(4), pixel_area_mm2=1.0, slab_height_mm=1.0,
                        mesh="tumor.ply")  # fmt: skip


def test_tumour_surface_empty_mask_gives_empty_mesh_and_closed_check():
    from tumor3d.pipeline import is_closed_surface, tumour_surface

    empty = tumour_surface(np.zeros((3, 4, 4), bool), np.eye(4))
    assert empty.is_empty and not is_closed_surface(empty)
    mask = np.zeros((5, 6, 6), bool)
    mask[1:4, 2:5, 2:5] = True
    mesh = tumour_surface(mask, np.eye(4))
    assert not mesh.is_empty and is_closed_surface(mesh)
