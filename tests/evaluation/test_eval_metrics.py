"""Tests of tumor3d.evaluation.metrics against naive references and analytic cases."""

from __future__ import annotations

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.evaluation import metrics as m


def _ball(shape, centre, radius, spacing=(1.0, 1.0, 1.0)):
    axes = [np.arange(n) * s for n, s in zip(shape, spacing, strict=True)]
    grids = np.meshgrid(*axes, indexing="ij")
    r2 = sum((g - c) ** 2 for g, c in zip(grids, centre, strict=True))
    return r2 <= radius**2


# ----------------------------------------------------------------------------- overlap


def _naive_dice(a, b):
    inter = sum(1 for x, y in zip(a.ravel(), b.ravel(), strict=True) if x and y)
    return 2 * inter / (int(a.sum()) + int(b.sum()))


def test_dice_jaccard_match_naive_on_random_masks():
    rng = np.random.default_rng(0)
    for _ in range(20):
        a = rng.random((6, 7, 5)) < 0.4
        b = rng.random((6, 7, 5)) < 0.5
        d = m.dice(a, b)
        assert d == pytest.approx(_naive_dice(a, b))
        j = m.jaccard(a, b)
        assert j == pytest.approx(d / (2 - d))  # the Dice-Jaccard identity


def test_dice_hand_cases():
    a = np.array([1, 1, 0, 0], dtype=bool)
    b = np.array([0, 1, 1, 0], dtype=bool)
    assert m.dice(a, b) == pytest.approx(0.5)
    assert m.jaccard(a, b) == pytest.approx(1 / 3)
    assert m.dice(a, a) == 1.0
    assert m.dice(a, np.zeros(4, bool)) == 0.0
    assert np.isnan(m.dice(np.zeros(4, bool), np.zeros(4, bool)))
    assert np.isnan(m.jaccard(np.zeros(4, bool), np.zeros(4, bool)))


def test_overlap_bad_input():
    with pytest.raises(InputError, match="same shape"):
        m.dice(np.zeros(3, bool), np.zeros(4, bool))
    with pytest.raises(InputError, match="binary"):
        m.dice(np.array([0, 2]), np.array([0, 1]))
    with pytest.raises(TypeError):
        m.dice([0, 1], np.array([0, 1]))


# ----------------------------------------------------------------------------- counts


def test_eq9_and_signed_error():
    assert m.relative_error_percent(90, 100) == pytest.approx(10.0)
    assert m.relative_error_percent(110, 100) == pytest.approx(10.0)
    assert np.isnan(m.relative_error_percent(5, 0))
    assert m.signed_percent_error(90.0, 100.0) == pytest.approx(-10.0)
    assert m.signed_percent_error(125.0, 100.0) == pytest.approx(25.0)
    with pytest.raises(InputError):
        m.relative_error_percent(-1, 10)
    with pytest.raises(TypeError):
        m.relative_error_percent("3", 10)


def test_slice_confusion_matches_naive_count():
    rng = np.random.default_rng(1)
    pred = rng.random(50) < 0.5
    ref = rng.integers(0, 3, size=50) * (rng.random(50) < 0.5)
    c = m.slice_confusion(pred, ref)
    naive = {"tp": 0, "fp": 0, "tn": 0, "fn": 0}
    for p, g in zip(pred, ref, strict=True):
        key = ("t" if p == (g > 0) else "f") + ("p" if p else "n")
        naive[key] += 1
    assert (c.tp, c.fp, c.tn, c.fn) == (naive["tp"], naive["fp"], naive["tn"], naive["fn"])
    assert c.tp + c.fp + c.tn + c.fn == 50
    assert c.sensitivity == pytest.approx(c.tp / (c.tp + c.fn))
    pooled = c + c
    assert pooled.tp == 2 * c.tp and pooled.specificity == pytest.approx(c.specificity)


def test_slice_confusion_bad_input():
    with pytest.raises(InputError, match="1-D"):
        m.slice_confusion(np.zeros(3, bool), np.zeros(4, int))
    with pytest.raises(InputError, match="non-negative"):
        m.slice_confusion(np.zeros(2, bool), np.array([1, -1]))


def test_bland_altman_against_hand_computation():
    ref = np.array([10.0, 20.0, 30.0, 40.0])
    est = np.array([11.0, 19.0, 33.0, 41.0])
    d = est - ref  # 1, -1, 3, 1
    ba = m.bland_altman(est, ref)
    mean = d.sum() / 4
    sd = np.sqrt(((d - mean) ** 2).sum() / 3)
    assert ba.bias == pytest.approx(1.0) and ba.bias == pytest.approx(mean)
    assert ba.sd == pytest.approx(sd)
    assert ba.loa_low == pytest.approx(mean - 1.96 * sd)
    assert ba.loa_high == pytest.approx(mean + 1.96 * sd)
    assert ba.n == 4
    one = m.bland_altman([2.0, np.nan], [1.0, 1.0])
    assert one.n == 1 and one.bias == 1.0 and np.isnan(one.sd)
    assert m.bland_altman([], []).n == 0


# ----------------------------------------------------------------------------- surfaces


def _naive_directed(a, b, spacing):
    """Brute force: every boundary voxel of a to every boundary voxel of b."""
    pa = np.argwhere(m.boundary_voxels(a)) * np.asarray(spacing)
    pb = np.argwhere(m.boundary_voxels(b)) * np.asarray(spacing)
    d = np.sqrt(((pa[:, None, :] - pb[None, :, :]) ** 2).sum(axis=2))
    return d.min(axis=1)


def test_boundary_voxels_hand_case():
    cube = np.zeros((5, 5, 5), bool)
    cube[1:4, 1:4, 1:4] = True
    b = m.boundary_voxels(cube)
    assert b.sum() == 27 - 1  # only the centre voxel is interior
    assert not b[2, 2, 2]
    full = np.ones((3, 3, 3), bool)
    assert m.boundary_voxels(full).sum() == 26  # the volume border counts as outside


def test_surface_distances_match_brute_force_anisotropic():
    rng = np.random.default_rng(2)
    spacing = (2.5, 0.7, 1.1)
    for _ in range(5):
        a = np.zeros((9, 12, 10), bool)
        b = np.zeros_like(a)
        a[rng.integers(0, 4) : rng.integers(5, 9), 2:9, rng.integers(0, 5) : 9] = True
        b[2:7, rng.integers(0, 5) : rng.integers(6, 12), 1 : rng.integers(3, 10)] = True
        a |= rng.random(a.shape) < 0.05
        got = m.surface_distances_mm(a, b, spacing)
        want_ab, want_ba = _naive_directed(a, b, spacing), _naive_directed(b, a, spacing)
        np.testing.assert_allclose(np.sort(got.pred_to_ref), np.sort(want_ab))
        np.testing.assert_allclose(np.sort(got.ref_to_pred), np.sort(want_ba))
        hd95, hdmax = m.hausdorff_mm(got)
        naive_all = [_naive_directed(a, b, spacing), _naive_directed(b, a, spacing)]
        assert hdmax == pytest.approx(max(x.max() for x in naive_all))
        assert hd95 == pytest.approx(max(np.percentile(x, 95) for x in naive_all))


@pytest.mark.parametrize(
    ("spacing", "r1", "r2"), [((1.0, 1.0, 1.0), 6.0, 11.0), ((2.0, 0.8, 0.8), 5.0, 13.0)]
)
def test_concentric_spheres_hausdorff_is_radius_difference(spacing, r1, r2):
    shape = tuple(int(np.ceil(32 / s)) for s in spacing)
    centre = tuple(n * s / 2 for n, s in zip(shape, spacing, strict=True))
    inner = _ball(shape, centre, r1, spacing)
    outer = _ball(shape, centre, r2, spacing)
    hd95, hdmax = m.hausdorff_mm(m.surface_distances_mm(inner, outer, spacing))
    voxel_diag = float(np.linalg.norm(spacing))
    assert abs(hdmax - (r2 - r1)) <= voxel_diag
    assert abs(hd95 - (r2 - r1)) <= voxel_diag
    assert hd95 <= hdmax
    # identical masks: zero distance
    same = m.hausdorff_mm(m.surface_distances_mm(outer, outer, spacing))
    assert same == (0.0, 0.0)


def test_world_distances_equal_grid_distances_and_handle_other_grid():
    spacing = (2.0, 1.0, 1.0)
    shape = (16, 32, 32)
    centre = (16.0, 16.0, 16.0)
    a = _ball(shape, centre, 7.0, spacing)
    b = _ball(shape, centre, 10.0, spacing)
    aff = np.diag([*spacing, 1.0])
    grid = m.surface_distances_mm(a, b, spacing)
    world = m.surface_distances_world_mm(a, aff, b, aff)
    np.testing.assert_allclose(np.sort(world.pred_to_ref), np.sort(grid.pred_to_ref))
    np.testing.assert_allclose(np.sort(world.ref_to_pred), np.sort(grid.ref_to_pred))
    # the same inner ball on a finer, shifted grid: still about 3 mm apart
    fine_aff = np.diag([0.5, 0.5, 0.5, 1.0])
    fine_aff[:3, 3] = 0.25
    fshape = (64, 64, 64)
    fa = _ball(fshape, tuple(c - 0.25 for c in centre), 7.0, (0.5, 0.5, 0.5))
    _, hdmax = m.hausdorff_mm(m.surface_distances_world_mm(fa, fine_aff, b, aff))
    assert abs(hdmax - 3.0) <= float(np.linalg.norm(spacing))


def test_surface_distances_empty_and_bad_input():
    a = np.zeros((4, 4, 4), bool)
    b = a.copy()
    b[1:3, 1:3, 1:3] = True
    d = m.surface_distances_mm(a, b, 1.0)
    assert not d.defined
    assert all(np.isnan(v) for v in m.hausdorff_mm(d))
    with pytest.raises(InputError, match="spacing"):
        m.surface_distances_mm(b, b, (1.0, -1.0, 1.0))
    with pytest.raises(InputError, match="percentile"):
        m.hausdorff_mm(m.surface_distances_mm(b, b, 1.0), 0.0)
    with pytest.raises(InputError, match="singular"):
        m.surface_distances_world_mm(b, np.zeros((4, 4)), b, np.eye(4))


def test_inputs_not_modified():
    a = np.zeros((5, 5, 5), bool)
    a[1:4, 1:4, 1:4] = True
    before = a.copy()
    for fn in (lambda: m.dice(a, a), lambda: m.surface_distances_mm(a, a, (1, 2, 3))):
        fn()
    assert np.array_equal(a, before)


def test_cropping_does_not_change_distances():
    # masks in a corner of a big volume: the crop must give the brute-force result
    a = np.zeros((20, 20, 20), bool)
    b = np.zeros_like(a)
    a[0:3, 0:4, 0:2] = True
    b[1:5, 2:3, 0:6] = True
    got = m.surface_distances_mm(a, b, (1.5, 1.0, 0.5))
    want = _naive_directed(a, b, (1.5, 1.0, 0.5))
    np.testing.assert_allclose(np.sort(got.pred_to_ref), np.sort(want))


def test_hd95_is_the_larger_directed_percentile():
    # b = a plus an equal cube 10 voxels away: a->b all 0, b->a half about 10 mm
    a = np.zeros((8, 8, 30), bool)
    a[2:6, 2:6, 2:6] = True
    b = a.copy()
    b[2:6, 2:6, 16:20] = True
    d = m.surface_distances_mm(a, b, 1.0)
    assert d.pred_to_ref.max() == 0.0
    hd95, hdmax = m.hausdorff_mm(d)
    assert hd95 == pytest.approx(np.percentile(d.ref_to_pred, 95))
    assert hd95 >= 10.0 and hdmax == pytest.approx(19.0 - 5.0)


def test_point_set_distances_brute_force_and_sphere_meshes():
    rng = np.random.default_rng(3)
    a, b = rng.random((40, 3)) * 10, rng.random((25, 3)) * 10
    d = m.point_set_distances_mm(a, b)
    brute = np.sqrt(((a[:, None] - b[None]) ** 2).sum(-1))
    np.testing.assert_allclose(d.pred_to_ref, brute.min(axis=1))
    np.testing.assert_allclose(d.ref_to_pred, brute.min(axis=0))
    # marching-cubes surfaces of two concentric balls (anisotropic voxels): HD = r2 - r1
    from tumor3d.geometry.surface import extract_surface

    spacing = (2.0, 1.0, 1.0)  # (z, y, x)
    shape = (20, 40, 40)
    centre = (20.0, 20.0, 20.0)
    aff = np.diag([spacing[2], spacing[1], spacing[0], 1.0])  # (x, y, z) -> mm
    inner = extract_surface(_ball(shape, centre, 8.0, spacing), aff)
    outer = extract_surface(_ball(shape, centre, 14.0, spacing), aff)
    hd95, hdmax = m.hausdorff_mm(m.point_set_distances_mm(inner.vertices, outer.vertices))
    assert abs(hdmax - 6.0) <= float(np.linalg.norm(spacing))
    assert abs(hd95 - 6.0) <= float(np.linalg.norm(spacing))
    assert not m.point_set_distances_mm(np.zeros((0, 3)), b).defined
    with pytest.raises(InputError, match=r"\(n, 3\)"):
        m.point_set_distances_mm(np.zeros((4, 2)), b)
