"""Tests of thick-slice emulation and grid helpers (tumor3d.evaluation.emulate/grids)."""

from __future__ import annotations

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.evaluation.emulate import (
    emulate_thick_labels,
    emulate_thick_slices,
    thick_slice_plan,
)
from tumor3d.evaluation.grids import grids_overlap, resample_nearest, same_grid, world_bounds_mm


def test_plan_5mm_step_2mm_thick_from_1mm():
    plan = thick_slice_plan(155, 1.0, step_mm=5.0, thickness_mm=2.0)
    # thick j = thin slices 5j and 5j+1; 31 complete thick slices (the last uses 150, 151)
    assert plan.shape == (31, 2)
    np.testing.assert_array_equal(plan[0], [0, 1])
    np.testing.assert_array_equal(plan[1], [5, 6])
    np.testing.assert_array_equal(plan[-1], [150, 151])
    off = thick_slice_plan(155, 1.0, step_mm=5.0, thickness_mm=2.0, offset=3)
    np.testing.assert_array_equal(off[0], [3, 4])
    assert off.shape == (31, 2) and off[-1, -1] == 154
    half = thick_slice_plan(20, 0.5, step_mm=2.0, thickness_mm=1.5)  # k = 4, m = 3
    np.testing.assert_array_equal(half[:2], [[0, 1, 2], [4, 5, 6]])
    assert half.shape == (5, 3)


def test_plan_errors():
    with pytest.raises(InputError, match="already thicker"):
        thick_slice_plan(30, 6.5, step_mm=5.0, thickness_mm=2.0)
    with pytest.raises(InputError, match="whole multiple"):
        thick_slice_plan(30, 1.0, step_mm=5.5, thickness_mm=2.0)
    with pytest.raises(InputError, match="exceeds"):
        thick_slice_plan(30, 1.0, step_mm=3.0, thickness_mm=4.0)
    with pytest.raises(InputError, match="at least 2"):
        thick_slice_plan(6, 1.0, step_mm=5.0, thickness_mm=2.0)


def test_emulated_image_is_mean_of_named_thin_slices_along_any_axis():
    rng = np.random.default_rng(0)
    thin = rng.random((7, 23, 9)).astype(np.float32)
    aff = np.array([[-0.9, 0, 0, 10], [0, 0, 1.0, -5], [0, 1.0, 0, 3], [0, 0, 0, 1]])
    before = thin.copy()
    out = emulate_thick_slices(thin, aff, axis=1, step_mm=5.0, thickness_mm=2.0)
    assert np.array_equal(thin, before)
    # thick slices from thin 0-1, 5-6, ..., 20-21
    assert out.volume.shape == (7, 5, 9) and out.volume.dtype == np.float32
    for j, rows in enumerate(out.thin_indices):
        np.testing.assert_allclose(out.volume[:, j, :], thin[:, rows, :].mean(axis=1), rtol=1e-6)
    assert (out.step_mm, out.thickness_mm, out.gap_mm) == (5.0, 2.0, 3.0)
    # world position of thick slice j = the mean position of its thin slices
    for j, rows in enumerate(out.thin_indices):
        thick_pt = out.affine @ np.array([2.0, j, 4.0, 1.0])
        thin_pt = aff @ np.array([2.0, rows.mean(), 4.0, 1.0])
        np.testing.assert_allclose(thick_pt, thin_pt, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(out.affine[:3, 1]), 5.0)


def test_emulated_label_uses_half_rule():
    thin = np.zeros((12, 3, 3), bool)
    thin[0, 0, 0] = True  # thick 0 = thin {0, 1}: 1 of 2 -> mean 0.5 -> tumour
    thin[5:7, 1, 1] = True  # thick 1 = {5, 6}: both -> tumour
    thin[7, 2, 2] = True  # thin 7 is in no thick slice (gap)
    aff = np.eye(4)
    lab = emulate_thick_labels(thin, aff, axis=0, step_mm=5.0, thickness_mm=2.0)
    assert lab.volume.dtype == bool and lab.volume.shape == (3, 3, 3)  # {0,1} {5,6} {10,11}
    assert lab.volume[0, 0, 0] and lab.volume[1, 1, 1]
    assert lab.volume.sum() == 2
    three = np.zeros((9, 1, 1), bool)
    three[0:1] = True  # 1 of 3 thin slices: 0.33 < 0.5 -> no tumour
    three[3:5] = True  # 2 of 3: tumour
    lab3 = emulate_thick_labels(three, aff, axis=0, step_mm=3.0, thickness_mm=3.0)
    np.testing.assert_array_equal(lab3.volume[:, 0, 0], [False, True, False])
    with pytest.raises(InputError, match="binary"):
        emulate_thick_labels(np.full((10, 2, 2), 2), aff, axis=0, step_mm=5.0, thickness_mm=2.0)


def test_emulation_bad_input():
    aff = np.eye(4)
    with pytest.raises(TypeError):
        emulate_thick_slices([[1]], aff, axis=0, step_mm=5.0, thickness_mm=2.0)
    with pytest.raises(InputError, match="axis"):
        emulate_thick_slices(np.zeros((10, 2, 2)), aff, axis=3, step_mm=5.0, thickness_mm=2.0)
    with pytest.raises(InputError, match="already thicker"):
        emulate_thick_slices(
            np.zeros((10, 2, 2)), np.diag([6.0, 1, 1, 1]), axis=0, step_mm=5.0, thickness_mm=2.0
        )


def test_grids_overlap_and_resample():
    aff = np.diag([1.0, 1.0, 1.0, 1.0])
    lo, hi = world_bounds_mm((4, 5, 6), aff)
    np.testing.assert_allclose(lo, [-0.5, -0.5, -0.5])
    np.testing.assert_allclose(hi, [3.5, 4.5, 5.5])
    far = aff.copy()
    far[:3, 3] = [100, 0, 0]
    assert grids_overlap((4, 5, 6), aff, (4, 5, 6), aff)
    assert not grids_overlap((4, 5, 6), aff, (4, 5, 6), far)
    assert same_grid((4, 5, 6), aff, (4, 5, 6), aff.copy())
    # a label on a 2x coarser grid sampled at fine voxel centres
    coarse = np.arange(8, dtype=np.uint8).reshape(2, 2, 2)
    caff = np.diag([2.0, 2.0, 2.0, 1.0])
    caff[:3, 3] = 0.5  # coarse voxel 0 spans fine voxels 0 and 1
    fine = resample_nearest(coarse, caff, (4, 4, 4), aff)
    naive = np.zeros((4, 4, 4), np.uint8)
    for idx in np.ndindex(4, 4, 4):
        src = np.linalg.solve(caff, np.array([*idx, 1.0]))[:3]
        r = np.floor(src + 0.5 + 1e-6).astype(int)
        if np.all(r >= 0) and np.all(r < 2):
            naive[idx] = coarse[tuple(r)]
    np.testing.assert_array_equal(fine, naive)
    np.testing.assert_array_equal(fine[::2, ::2, ::2], coarse)
    outside = resample_nearest(coarse.astype(bool), far, (2, 2, 2), aff)
    assert outside.dtype == bool and not outside.any()
