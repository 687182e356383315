"""Tests of tumor3d.geometry.interpolate (spec section 4, Algorithm 1)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tumor3d.config import InterpolateConfig
from tumor3d.errors import InputError
from tumor3d.geometry.interpolate import (
    InterpolatedStack,
    chamfer_distance,
    interpolate_gray_slices,
    interpolate_pair,
    interpolate_stack,
    interpolation_error_percent,
    leave_one_out_error,
    signed_distance,
    slices_between_auto,
)

METHODS = ("enhanced", "enhanced-edt", "shape", "shape-edt", "linear")
#: Algorithm 1 of the paper, literally
SE = {"method": "enhanced", "parts": "whole"}
SQRT2 = math.sqrt(2.0)
# max of chamfer(1, sqrt2) / Euclidean, reached at 22.5 degrees
CHAMFER_MAX_RATIO = math.cos(math.pi / 8) + (SQRT2 - 1.0) * math.sin(math.pi / 8)


# --------------------------------------------------------------------------
# phantoms and naive references


def disk(shape, centre, radius):
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    return (yy - centre[0]) ** 2 + (xx - centre[1]) ** 2 <= radius**2


def ellipse(shape, centre, axes, angle):
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    y, x = yy - centre[0], xx - centre[1]
    c, s = math.cos(angle), math.sin(angle)
    u, v = c * x + s * y, -s * x + c * y
    return (u / axes[1]) ** 2 + (v / axes[0]) ** 2 <= 1.0


def centroid(mask):
    return np.argwhere(mask).mean(axis=0)


def random_blob(rng, shape, n_ellipses=3):
    out = np.zeros(shape, dtype=bool)
    for _ in range(n_ellipses):
        c = rng.uniform(0.3, 0.7, 2) * np.array(shape)
        ax = rng.uniform(3.0, 0.2 * min(shape), 2)
        out |= ellipse(shape, c, ax, rng.uniform(0, math.pi))
    return out


def drifting_sphere(radius_mm=20.0, drift=0.93, dz_mm=5.0, shape=(64, 96)):
    """Sphere sampled every dz (1 mm pixels) whose centre moves by ``drift`` mm in x per mm of z.

    A shear keeps the volume, so every slab's true volume is that of the sphere.
    """
    zs = np.arange(-22.0, 22.0 + 1e-9, dz_mm)
    masks = []
    for z in zs:
        r2 = radius_mm**2 - z**2
        c = (31.3, 40.2 + drift * (z - zs[0]))
        masks.append(disk(shape, c, math.sqrt(r2)) if r2 > 0 else np.zeros(shape, dtype=bool))
    return np.array(masks), zs


def sphere_segment_volume(radius, z_lo, z_hi):
    z_lo, z_hi = max(z_lo, -radius), min(z_hi, radius)

    def f(z):
        return radius**2 * z - z**3 / 3.0

    return math.pi * (f(z_hi) - f(z_lo))


# --------------------------------------------------------------------------
# interpolate_pair


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), t=st.floats(0.01, 0.99))
def test_identical_masks_are_returned_for_all_methods(seed, t):
    mask = random_blob(np.random.default_rng(seed), (40, 52))
    for method in METHODS:
        np.testing.assert_array_equal(interpolate_pair(mask, mask, t, method=method), mask)


def test_identical_masks_far_from_centre_are_not_clipped():
    # an L whose centroid is near the top-left corner: centring it on the grid
    # moves the arms past the opposite border, which must not cut them
    mask = np.zeros((40, 40), dtype=bool)
    mask[0:3, :] = True
    mask[:, 0:3] = True
    for t in (0.2, 0.5, 0.9):
        for method in METHODS:
            np.testing.assert_array_equal(interpolate_pair(mask, mask, t, method=method), mask)


@pytest.mark.parametrize("centre", [(47.5, 47.5), (40.3, 51.7)])
@pytest.mark.parametrize(("r1", "r2"), [(8.0, 24.0), (5.0, 30.0), (12.0, 16.0)])
@pytest.mark.parametrize("t", [0.25, 0.5, 0.75])
@pytest.mark.parametrize("method", ["enhanced", "shape-edt", "enhanced-edt"])
def test_concentric_disks_give_disk_of_interpolated_radius(centre, r1, r2, t, method):
    shape = (96, 96)
    out = interpolate_pair(disk(shape, centre, r1), disk(shape, centre, r2), t, method=method)
    r_t = (1 - t) * r1 + t * r2
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    rho = np.hypot(yy - centre[0], xx - centre[1])
    assert np.all(out[rho <= r_t - 1.0])
    assert not np.any(out[rho >= r_t + 1.0])
    assert abs(math.sqrt(out.sum() / math.pi) - r_t) <= 1.0


@pytest.mark.parametrize("displacement", [(14.0, 9.0), (0.0, 20.0), (20.0, 20.0)])
def test_displaced_disks_enhanced_keeps_disk_while_so_shrinks(displacement):
    """Enhanced moves the disk along the centroid path; SO (no alignment) gives a lens.

    Without alignment, SO thresholds the mean of two distance maps whose
    objects only partly overlap: the result is the lens-shaped region
    around the overlap (empty when the disks are far apart), so its area
    falls well below the disk area once the displacement exceeds the radius.
    """
    shape, r, t = (96, 96), 12.0, 0.5
    a = disk(shape, (40.2, 30.6), r)
    b = disk(shape, (40.2 + displacement[0], 30.6 + displacement[1]), r)
    assert math.hypot(*displacement) > r
    enhanced = interpolate_pair(a, b, t, **SE)
    so = interpolate_pair(a, b, t, method="shape")
    c_z = (1 - t) * centroid(a) + t * centroid(b)
    assert abs(enhanced.sum() - a.sum()) <= 0.03 * a.sum()
    assert np.all(np.abs(centroid(enhanced) - c_z) <= 1.0)
    # the output is the (equal) disk around the interpolated centre, up to rasterisation
    assert interpolation_error_percent(disk(shape, c_z, r), enhanced) < 10.0
    assert so.sum() < 0.8 * a.sum()


def test_centroid_follows_interpolated_path():
    rng = np.random.default_rng(11)
    shape = (80, 90)
    for _ in range(20):
        a = ellipse(shape, rng.uniform(25, 55, 2), rng.uniform(4, 14, 2), rng.uniform(0, 3))
        b = ellipse(shape, rng.uniform(25, 55, 2), rng.uniform(4, 14, 2), rng.uniform(0, 3))
        t = float(rng.uniform(0.05, 0.95))
        out = interpolate_pair(a, b, t, **SE)
        assert out.any()
        c_z = (1 - t) * centroid(a) + t * centroid(b)
        assert np.all(np.abs(centroid(out) - c_z) <= 0.5 + 1e-9)


def test_objects_at_the_border_stay_there():
    shape = (64, 64)
    # a disk cut by the left border and a small one at the same place
    a = disk(shape, (32.0, 3.0), 14.0)
    b = disk(shape, (32.0, 3.0), 4.0)
    for method in METHODS:
        for t in (0.3, 0.5, 0.7):
            out = interpolate_pair(a, b, t, method=method)
            assert out[:, 0].any()
            assert not out[:, shape[1] // 2 :].any()


@pytest.mark.parametrize("axis", [0, 1])
def test_zero_fill_shift_never_wraps_around(axis):
    """Pixels moved past the border are dropped, never wrapped to the far side.

    Padding both masks by an even number of empty rows/columns before the
    border moves the grid centre by an integer, so the padded result cropped
    back must equal the direct result; the padding shows what fell off.
    """
    rng = np.random.default_rng(2024 + axis)
    shape, pad = (48, 48), 30
    widths = [(0, 0), (0, 0)]
    widths[axis] = (pad, 0)
    n_clipped = 0
    for _ in range(60):
        centres = []
        for _ in range(2):
            c = [rng.uniform(10, 38), rng.uniform(10, 38)]
            c[axis] = rng.uniform(-3, 8)
            centres.append(c)
        a = ellipse(shape, centres[0], rng.uniform(2, 15, 2), rng.uniform(0, math.pi))
        b = ellipse(shape, centres[1], rng.uniform(2, 15, 2), rng.uniform(0, math.pi))
        if not (a.any() and b.any()):
            continue
        out = interpolate_pair(a, b, 0.5, **SE)
        big = interpolate_pair(np.pad(a, widths), np.pad(b, widths), 0.5, **SE)
        np.testing.assert_array_equal(np.take(big, np.arange(pad, pad + 48), axis=axis), out)
        n_clipped += bool(np.take(big, np.arange(pad), axis=axis).any())
    assert n_clipped >= 3  # the border really cut some results


def test_linear_method_thresholds_the_mask_average():
    a = np.zeros((10, 10), dtype=bool)
    a[2:6, 2:6] = True
    b = np.zeros((10, 10), dtype=bool)
    b[4:8, 3:9] = True
    np.testing.assert_array_equal(interpolate_pair(a, b, 0.3, method="linear"), a)
    np.testing.assert_array_equal(interpolate_pair(a, b, 0.7, method="linear"), b)
    np.testing.assert_array_equal(interpolate_pair(a, b, 0.5, method="linear"), a | b)


@pytest.mark.parametrize("method", METHODS)
def test_empty_input_gives_empty_output(method):
    a = disk((20, 20), (10, 10), 5)
    empty = np.zeros_like(a)
    assert not interpolate_pair(a, empty, 0.5, method=method).any()
    assert not interpolate_pair(empty, a, 0.5, method=method).any()


def test_inputs_are_not_modified():
    rng = np.random.default_rng(3)
    a = random_blob(rng, (30, 30))
    b = random_blob(rng, (30, 30))
    stack = np.array([a, b, a])
    copies = [a.copy(), b.copy(), stack.copy()]
    for method in METHODS:
        interpolate_pair(a, b, 0.4, method=method)
        interpolate_stack(stack, method=method, slices_between=2)
        leave_one_out_error(stack, 1, method=method)
    chamfer_distance(a)
    signed_distance(b, metric="taxicab")
    interpolation_error_percent(a, b)
    for orig, now in zip(copies, [a, b, stack], strict=True):
        np.testing.assert_array_equal(orig, now)


# --------------------------------------------------------------------------
# interpolate_stack


def _stack_with_gaps():
    shape = (40, 48)
    masks = np.zeros((7,) + shape, dtype=bool)
    for k, (cy, cx, r) in enumerate(
        [(20, 15, 6), (20, 18, 8), (21, 22, 9), (0, 0, 0), (19, 27, 7), (20, 30, 5), (0, 0, 0)]
    ):
        if r:
            masks[k] = disk(shape, (cy, cx), r)
    return masks


@pytest.mark.parametrize("method", METHODS)
def test_interpolate_stack_layout(method):
    masks = _stack_with_gaps()
    m = 3
    result = interpolate_stack(masks, method=method, slices_between=m)
    n = len(masks)
    z = (n - 1) * (m + 1) + 1
    assert isinstance(result, InterpolatedStack)
    assert result.mask.shape == (z,) + masks.shape[1:]
    assert result.mask.dtype == bool
    assert result.slices_between == m
    np.testing.assert_allclose(result.source_index, np.arange(z) / (m + 1))
    # originals restored unchanged
    np.testing.assert_array_equal(result.mask[:: m + 1], masks)
    np.testing.assert_array_equal(result.original, np.arange(z) % (m + 1) == 0)
    nonempty = masks.any(axis=(1, 2))
    for k in range(n - 1):
        inserted = slice(k * (m + 1) + 1, (k + 1) * (m + 1))
        both = bool(nonempty[k] and nonempty[k + 1])
        assert np.all(result.interpolated[inserted] == both)
        if both:
            assert result.mask[inserted].any(axis=(1, 2)).all()
            for j in range(1, m + 1):
                expected = interpolate_pair(masks[k], masks[k + 1], j / (m + 1), method=method)
                np.testing.assert_array_equal(result.mask[k * (m + 1) + j], expected)
        else:
            assert not result.mask[inserted].any()
    assert not result.interpolated[:: m + 1].any()
    with pytest.raises(ValueError, match="read-only"):
        result.mask[0, 0, 0] = True


def test_interpolate_stack_without_inserted_slices_is_identity():
    masks = _stack_with_gaps()
    result = interpolate_stack(masks, slices_between=0)
    np.testing.assert_array_equal(result.mask, masks)
    assert not result.interpolated.any()
    single = interpolate_stack(masks[:1], slices_between=3)
    np.testing.assert_array_equal(single.mask, masks[:1])


def test_interpolate_stack_accepts_config_and_resolves_auto_count():
    masks = _stack_with_gaps()
    cfg = InterpolateConfig()
    assert cfg.slices_between is None
    result = interpolate_stack(
        masks, **cfg.model_dump(), slice_step_mm=5.0, pixel_spacing_mm=(1.0, 1.0)
    )
    assert result.slices_between == 4
    assert result.mask.shape[0] == (len(masks) - 1) * 5 + 1
    fixed = interpolate_stack(masks, **InterpolateConfig(slices_between=2).model_dump())
    assert fixed.slices_between == 2


def test_fine_affine_maps_fine_slices_to_original_world_positions():
    rng = np.random.default_rng(5)
    affine = np.eye(4)
    affine[:3, :3] = rng.normal(size=(3, 3))
    affine[:3, 3] = rng.normal(size=3) * 50
    masks = _stack_with_gaps()
    m = 4
    result = interpolate_stack(masks, slices_between=m)
    fine = result.fine_affine(affine)
    for j in range(result.mask.shape[0]):
        x, y = float(rng.integers(0, 48)), float(rng.integers(0, 40))
        expected = affine @ np.array([x, y, j / (m + 1), 1.0])
        np.testing.assert_allclose(fine @ np.array([x, y, j, 1.0]), expected, atol=1e-9)
    np.testing.assert_allclose(fine[:, [0, 1, 3]], affine[:, [0, 1, 3]])
    np.testing.assert_allclose(result.fine_affine(affine)[:3, 2] * (m + 1), affine[:3, 2])


@pytest.mark.parametrize(
    ("step", "spacing", "expected"),
    [
        (5.0, (1.0, 1.0), 4),
        (5.0, (0.5, 0.5), 9),
        (1.0, (2.0, 2.0), 0),
        (5.0, (2.0, 2.0), 2),
        (3.0, (1.0, 1.0), 2),
        (5.0, (0.9375, 0.9375), 4),
        (6.5, (0.78, 0.78), 7),
    ],
)
def test_slices_between_auto(step, spacing, expected):
    assert slices_between_auto(step, spacing) == expected


# --------------------------------------------------------------------------
# drifting sphere phantom and Eq. 10


def test_enhanced_beats_shape_based_on_drifting_sphere():
    masks, zs = drifting_sphere()
    m = 4  # 5 mm steps, 1 mm pixels -> 1 mm fine slices
    nonempty = np.flatnonzero(masks.any(axis=(1, 2)))
    # true volume of the part the stack can cover: half a fine slab beyond the end slices
    v_true = sphere_segment_volume(20.0, zs[nonempty[0]] - 0.5, zs[nonempty[-1]] + 0.5)
    volumes = {}
    for method in ("enhanced", "shape"):
        fine = interpolate_stack(masks, method=method, slices_between=m).mask
        volumes[method] = fine.sum() * 1.0 * 5.0 / (m + 1)  # mm^3
    err = {k: abs(v - v_true) / v_true for k, v in volumes.items()}
    assert err["enhanced"] < err["shape"]
    assert err["enhanced"] < 0.03

    interior = [k for k in range(1, len(masks) - 1) if masks[k - 1].any() and masks[k + 1].any()]
    assert len(interior) >= 5
    loo = {
        method: np.array([leave_one_out_error(masks, k, method=method) for k in interior])
        for method in METHODS
    }
    # the paper's claim (Table 4): SE < SO < LG
    assert np.all(loo["enhanced"] < loo["shape"])
    assert loo["enhanced"].mean() < loo["shape"].mean() < loo["linear"].mean()
    # the exact distance does at least as well as the chamfer one on a round object
    assert loo["enhanced-edt"].mean() <= loo["enhanced"].mean() + 0.5


def test_interpolation_error_percent_known_values():
    s = np.zeros((6, 6), dtype=bool)
    s[1:3, 1:5] = True  # 8 pixels
    e = np.zeros_like(s)
    e[2:4, 1:5] = True  # overlaps 4, adds 4
    assert interpolation_error_percent(s, e) == pytest.approx(100.0)
    assert interpolation_error_percent(s, s) == 0.0
    assert interpolation_error_percent(s, np.zeros_like(s)) == pytest.approx(100.0)
    assert interpolation_error_percent(s, s | (np.arange(6) == 5)[None, :]) == pytest.approx(75.0)


def test_leave_one_out_error_with_linear_union():
    # linear at t = 1/2 returns the union of the neighbours
    masks = np.zeros((3, 8, 8), dtype=bool)
    masks[0, 1:3, 1:5] = True  # 8 px
    masks[2, 4:6, 1:5] = True  # 8 px
    masks[1, 2:5, 1:5] = True  # 12 px; union differs on rows 1, 3 (out) and 5 (in): 12 px
    assert leave_one_out_error(masks, 1, method="linear") == pytest.approx(100.0)
    expected = interpolation_error_percent(masks[1], interpolate_pair(masks[0], masks[2], 0.5))
    assert leave_one_out_error(masks, 1) == pytest.approx(expected)


# --------------------------------------------------------------------------
# validation


def test_validation_mask_dimensions():
    with pytest.raises(InputError, match="mask must be a 2-D mask"):
        chamfer_distance(np.zeros((2, 3, 4), dtype=bool))
    with pytest.raises(InputError, match="slice_masks must be a 3-D mask"):
        interpolate_stack(np.zeros((3, 4), dtype=bool), slices_between=1)


def test_validation_mask_size_zero():
    with pytest.raises(InputError, match="must not be empty"):
        signed_distance(np.zeros((0, 4), dtype=bool))


def test_validation_mask_not_binary():
    with pytest.raises(InputError, match="mask_a must be binary"):
        interpolate_pair(np.full((4, 4), 2), np.zeros((4, 4), bool), 0.5)
    with pytest.raises(InputError, match="must be binary"):
        chamfer_distance(np.array([["a", "b"]]))


def test_validation_shapes_differ():
    with pytest.raises(InputError, match="same shape"):
        interpolate_pair(np.zeros((4, 4), bool), np.zeros((4, 5), bool), 0.5)
    with pytest.raises(InputError, match="truth and estimate must have the same shape"):
        interpolation_error_percent(np.ones((4, 4), bool), np.ones((5, 4), bool))


@pytest.mark.parametrize("t", [0.0, 1.0, -0.5, 1.5, float("nan")])
def test_validation_t_outside_open_interval(t):
    with pytest.raises(InputError, match=r"t must lie in the open interval \(0, 1\)"):
        interpolate_pair(np.ones((4, 4), bool), np.ones((4, 4), bool), t)


def test_validation_t_not_a_number():
    with pytest.raises(InputError, match="t must be a number"):
        interpolate_pair(np.ones((4, 4), bool), np.ones((4, 4), bool), "half")


def test_validation_unknown_method_and_metric():
    with pytest.raises(InputError, match="method must be one of"):
        interpolate_pair(np.ones((4, 4), bool), np.ones((4, 4), bool), 0.5, method="cubic")
    with pytest.raises(InputError, match="method must be one of"):
        interpolate_stack(np.ones((2, 4, 4), bool), method="cubic", slices_between=1)
    with pytest.raises(InputError, match="metric must be one of"):
        signed_distance(np.ones((4, 4), bool), metric="manhattan")
    with pytest.raises(InputError, match="parts must be one of"):
        interpolate_pair(np.ones((4, 4), bool), np.ones((4, 4), bool), 0.5, parts="each")
    with pytest.raises(InputError, match="parts must be one of"):
        interpolate_stack(np.ones((2, 4, 4), bool), parts=None, slices_between=1)
    with pytest.raises(InputError, match="unknown end_caps"):
        interpolate_stack(np.ones((2, 4, 4), bool), end_caps="round", slices_between=1)
    with pytest.raises(InputError, match="pixel_spacing_mm must hold positive"):
        interpolate_pair(
            np.ones((4, 4), bool), np.ones((4, 4), bool), 0.5, pixel_spacing_mm=(1.0, -1.0)
        )


def test_validation_slices_between():
    masks = np.ones((2, 4, 4), bool)
    with pytest.raises(InputError, match="slices_between must be >= 0"):
        interpolate_stack(masks, slices_between=-1)
    with pytest.raises(InputError, match="slices_between must be an integer or None"):
        interpolate_stack(masks, slices_between=2.5)
    with pytest.raises(InputError, match="slice_step_mm and pixel_spacing_mm were not both"):
        interpolate_stack(masks, slices_between=None, slice_step_mm=5.0)


def test_validation_slices_between_auto():
    with pytest.raises(InputError, match="slice_step_mm must be a positive finite"):
        slices_between_auto(0.0, (1.0, 1.0))
    with pytest.raises(InputError, match="slice_step_mm must be a positive number"):
        slices_between_auto("five", (1.0, 1.0))
    with pytest.raises(InputError, match="pixel_spacing_mm must be a pair"):
        slices_between_auto(5.0, (1.0, 1.0, 1.0))
    with pytest.raises(InputError, match=r"pixel_spacing_mm\[1\] must be a positive finite"):
        slices_between_auto(5.0, (1.0, -1.0))


def test_validation_eq10_and_leave_one_out():
    with pytest.raises(InputError, match="truth holds no object pixel"):
        interpolation_error_percent(np.zeros((3, 3), bool), np.ones((3, 3), bool))
    masks = np.ones((3, 4, 4), bool)
    for k in (0, 2, 1.0):
        with pytest.raises(InputError, match="k must be an integer with 1 <= k <= n - 2"):
            leave_one_out_error(masks, k)


def test_validation_stack_object():
    result = interpolate_stack(np.ones((2, 4, 4), bool), slices_between=1)
    with pytest.raises(InputError, match="affine must be 4x4"):
        result.fine_affine(np.eye(3))
    with pytest.raises(ValueError, match="needs a \\(Z, y, x\\) mask"):
        InterpolatedStack(np.ones((3, 4, 4), bool), 1, np.arange(2), np.zeros(3, bool))
    with pytest.raises(ValueError, match="slices_between must be >= 0"):
        InterpolatedStack(np.ones((3, 4, 4), bool), -1, np.arange(3), np.zeros(3, bool))


# --------------------------------------------------------------------------
# several parts per slice


def _two_blobs(shape, c1, c2, r1, r2):
    return disk(shape, c1, r1) | disk(shape, c2, r2)


@pytest.mark.parametrize("method", ["enhanced", "enhanced-edt"])
def test_parts_drifting_apart_are_each_aligned(method):
    """Two parts moving in opposite directions: per-part alignment follows both.

    The whole-slice centroid does not move, so Algorithm 1 aligns nothing and
    interpolates two overlapping pairs as a lens each; matched parts give
    the two disks at their interpolated centres.
    """
    shape, r = (80, 100), 9.0
    a = _two_blobs(shape, (30.0, 25.0), (30.0, 70.0), r, r)
    b = _two_blobs(shape, (46.0, 25.0), (14.0, 70.0), r, r)
    truth = _two_blobs(shape, (38.0, 25.0), (22.0, 70.0), r, r)
    matched = interpolate_pair(a, b, 0.5, method=method, parts="matched")
    whole = interpolate_pair(a, b, 0.5, method=method, parts="whole")
    e_matched = interpolation_error_percent(truth, matched)
    e_whole = interpolation_error_percent(truth, whole)
    assert e_matched < 12.0
    assert e_whole > 2 * e_matched


@pytest.mark.parametrize("method", ["enhanced", "enhanced-edt", "shape", "shape-edt"])
def test_unmatched_part_shrinks_to_nothing(method):
    shape = (64, 96)
    big = disk(shape, (32.0, 30.0), 12.0)
    small = disk(shape, (32.0, 75.0), 6.0)
    a = big | small
    b = big.copy()
    areas = []
    for t in (0.1, 0.3, 0.5, 0.7, 0.9):
        out = interpolate_pair(a, b, t, method=method, parts="matched")
        np.testing.assert_array_equal(out[:, :50], big[:, :50])  # the matched part stays
        assert not (out & ~a).any()  # the lone part only erodes
        areas.append(int(out[:, 50:].sum()))
    assert areas[0] > 0
    assert all(x > y for x, y in zip(areas, areas[1:], strict=False)) or areas[-1] == 0
    assert areas[-1] <= 0.05 * small.sum()
    # and the same in the other direction (a part that appears)
    out = interpolate_pair(b, a, 0.9, method=method, parts="matched")
    assert out[:, 50:].sum() == areas[0]


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), t=st.floats(0.05, 0.95))
def test_one_part_each_matched_equals_whole(seed, t):
    """With one overlapping part per slice the matched method is the whole-slice method."""
    rng = np.random.default_rng(seed)
    shape = (48, 56)
    c = rng.uniform(18, 30, 2)
    a = ellipse(shape, c, rng.uniform(5, 12, 2), rng.uniform(0, math.pi))
    b = ellipse(shape, c + rng.uniform(-3, 3, 2), rng.uniform(5, 12, 2), rng.uniform(0, math.pi))
    for method in METHODS:
        np.testing.assert_array_equal(
            interpolate_pair(a, b, t, method=method, parts="matched"),
            interpolate_pair(a, b, t, method=method, parts="whole"),
        )


def test_part_that_splits_is_one_group():
    """A part overlapping two parts of the next slice is interpolated with both at once."""
    shape = (60, 80)
    a = ellipse(shape, (30.0, 40.0), (8.0, 25.0), 0.0)
    b = _two_blobs(shape, (30.0, 25.0), (30.0, 55.0), 8.0, 8.0)
    for method in ("shape", "shape-edt"):
        np.testing.assert_array_equal(
            interpolate_pair(a, b, 0.5, method=method, parts="matched"),
            interpolate_pair(a, b, 0.5, method=method, parts="whole"),
        )


def test_matching_after_alignment_for_aligned_methods():
    """Parts that moved past each other without overlap are matched after alignment."""
    shape = (60, 120)
    a = _two_blobs(shape, (30.0, 20.0), (30.0, 50.0), 5.0, 5.0)
    b = _two_blobs(shape, (30.0, 70.0), (30.0, 100.0), 5.0, 5.0)
    truth = _two_blobs(shape, (30.0, 45.0), (30.0, 75.0), 5.0, 5.0)
    out = interpolate_pair(a, b, 0.5, method="enhanced-edt", parts="matched")
    assert interpolation_error_percent(truth, out) < 15.0
    # without alignment nothing overlaps: every part shrinks in place
    so = interpolate_pair(a, b, 0.5, method="shape-edt", parts="matched")
    assert not (so & ~(a | b)).any()


def test_taper_per_part_keeps_small_parts_to_the_end():
    shape = (64, 96)
    big = disk(shape, (32.0, 30.0), 15.0)
    small = disk(shape, (32.0, 75.0), 4.0)
    masks = np.array([big | small, np.zeros(shape, bool)])
    m = 4
    whole = interpolate_stack(masks, slices_between=m, end_caps="taper", parts="whole")
    matched = interpolate_stack(masks, slices_between=m, end_caps="taper", parts="matched")
    # each part is its own cone: the small one lasts as many slices as the big one
    for j in range(1, m + 1):
        assert matched.mask[j, :, 50:].any() and matched.mask[j, :, :50].any()
        assert not (matched.mask[j] & ~masks[0]).any()
    # one cone over the whole slice erodes the small part away early
    assert not whole.mask[m, :, 50:].any()


def test_stack_without_tumour_and_unsorted_documented():
    empty = np.zeros((4, 10, 10), dtype=bool)
    for method in METHODS:
        st_ = interpolate_stack(empty, method=method, slices_between=2, end_caps="taper")
        assert st_.mask.shape == (10, 10, 10)
        assert not st_.mask.any() and not st_.interpolated.any()


def test_euclidean_methods_use_the_pixel_spacing():
    """Only the ratio dy/dx matters; anisotropic pixels change the result."""
    shape = (40, 40)
    a = ellipse(shape, (20.0, 14.0), (6.0, 6.0), 0.0)
    b = ellipse(shape, (20.0, 24.0), (9.0, 5.0), 0.4)
    for method in ("shape-edt", "enhanced-edt"):
        unit = interpolate_pair(a, b, 0.4, method=method)
        scaled = interpolate_pair(a, b, 0.4, method=method, pixel_spacing_mm=(0.7, 0.7))
        np.testing.assert_array_equal(unit, scaled)
        aniso = interpolate_pair(a, b, 0.4, method=method, pixel_spacing_mm=(0.5, 2.0))
        assert (aniso != unit).any()


# --------------------------------------------------------------------------
# gray-level interpolation (LG)


def test_gray_interpolation_is_linear_and_keeps_originals():
    rng = np.random.default_rng(9)
    images = rng.normal(size=(4, 6, 5))
    m = 3
    fine = interpolate_gray_slices(images, slices_between=m)
    assert fine.shape == (13, 6, 5)
    np.testing.assert_array_equal(fine[::4], images)
    for k in range(3):
        for j in range(1, 4):
            t = j / 4
            np.testing.assert_allclose(
                fine[4 * k + j], (1 - t) * images[k] + t * images[k + 1], rtol=1e-12
            )
    np.testing.assert_array_equal(interpolate_gray_slices(images, slices_between=0), images)
    # the mask variant is the thresholded gray interpolation of 0/1 images
    masks = _stack_with_gaps()[:3]  # three non-empty slices
    np.testing.assert_array_equal(
        interpolate_gray_slices(masks.astype(float), slices_between=2) >= 0.5,
        interpolate_stack(masks, method="linear", slices_between=2).mask,
    )


def test_gray_interpolation_validation():
    with pytest.raises(InputError, match="images must be a non-empty"):
        interpolate_gray_slices(np.zeros((3, 4)), slices_between=1)
    with pytest.raises(InputError, match="finite numbers"):
        interpolate_gray_slices(np.full((2, 3, 3), np.nan), slices_between=1)
    with pytest.raises(InputError, match="slices_between must be >= 0"):
        interpolate_gray_slices(np.zeros((2, 3, 3)), slices_between=-2)
    with pytest.raises(InputError, match="slices_between must be an integer"):
        interpolate_gray_slices(np.zeros((2, 3, 3)), slices_between=1.5)


def test_paper_yaml_is_algorithm_1_and_default_is_the_measured_choice():
    from pathlib import Path

    from tumor3d.config import parse_config

    configs = Path(__file__).resolve().parents[2] / "configs"
    paper = parse_config((configs / "paper.yaml").read_text(), source="paper.yaml").interpolate
    assert (paper.method, paper.parts, paper.end_caps) == ("enhanced", "whole", "none")
    default = InterpolateConfig()
    assert (default.method, default.parts, default.end_caps) == ("shape-edt", "matched", "taper")
    with pytest.raises(ValueError, match="parts"):
        InterpolateConfig(parts="each")


@pytest.mark.parametrize("method", ["shape", "shape-edt", "linear"])
def test_reversed_slice_order_gives_the_reversed_stack(method):
    """Order is not checked (masks carry no z); the documented result for reversed input.

    The unaligned methods are symmetric in (a, b, t) <-> (b, a, 1 - t), so the
    stack of reversed slices is the reversed stack, up to floating-point ties.
    """
    masks = _stack_with_gaps()
    fwd = interpolate_stack(masks, method=method, slices_between=3, end_caps="taper").mask
    rev = interpolate_stack(masks[::-1], method=method, slices_between=3, end_caps="taper").mask
    assert np.count_nonzero(fwd != rev[::-1]) <= 1e-3 * fwd.size
