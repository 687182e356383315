"""Tests of tumor3d.phantom: synthetic patients with known ground truth."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import ndimage

from tumor3d.errors import InputError
from tumor3d.phantom import (
    _MONOMIALS,
    TISSUE_INTENSITIES,
    PhantomPatient,
    TumorShape,
    _head_fields_many,
    _random_head,
    _render,
    make_phantom_patient,
    random_tumor_shape,
    tumor_volume_mm3,
)

SMALL = {"matrix_size": (96, 96), "n_slices": 10}  # 2.5 mm pixels, 240 mm FOV


@pytest.fixture(scope="module")
def small() -> PhantomPatient:
    return make_phantom_patient(5, **SMALL)


@pytest.fixture(scope="module")
def medium() -> PhantomPatient:
    # 1.875 mm pixels: fine enough for the partial-volume-free interior statistics
    return make_phantom_patient(11, matrix_size=(128, 128))


def _naive_inside(shape: TumorShape, pts: np.ndarray) -> np.ndarray:
    """Reference inside-test written straight from the TumorShape definition."""
    v = pts - shape.center_mm
    z = v[:, 2]
    k = np.arange(1, shape.shear_coefficients.shape[1] + 1)
    zp = z[:, None] ** k[None, :]
    v = v - np.stack(
        [zp @ shape.shear_coefficients[0], zp @ shape.shear_coefficients[1], np.zeros(len(v))],
        axis=1,
    )
    w = np.linalg.solve(shape.linear_map, v.T).T
    n = np.linalg.norm(w, axis=1)
    u = w / np.where(n > 0, n, 1.0)[:, None]
    r = shape.radius_mm * np.ones(len(w))
    for d, a, kap in zip(
        shape.bump_directions, shape.bump_amplitudes, shape.bump_kappas, strict=True
    ):
        r = r + shape.radius_mm * a * np.exp(kap * (u @ d - 1.0))
    return n <= r


def _voxel_centres(affine: np.ndarray, shape_zyx: tuple[int, int, int]) -> np.ndarray:
    k, j, i = np.meshgrid(*(np.arange(s) for s in shape_zyx), indexing="ij")
    idx = np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1).astype(float)
    return idx @ affine[:3, :3].T + affine[:3, 3]


# ---------------------------------------------------------------------------
# Exact volume
# ---------------------------------------------------------------------------


def test_sphere_volume_is_analytic():
    for radius in (3.0, 12.5, 20.0):
        ball = TumorShape.sphere((1.0, -2.0, 3.0), radius)
        assert tumor_volume_mm3(ball) == pytest.approx(4.0 / 3.0 * np.pi * radius**3, rel=1e-13)


def test_sheared_ellipsoid_volume_is_analytic():
    # no bumps: an ellipsoid with semi-axes R*sv(A); the shear keeps the volume
    rng = np.random.default_rng(0)
    lin = rng.normal(size=(3, 3)) + 2 * np.eye(3)
    shape = TumorShape(
        center_mm=(5, 5, 5),
        radius_mm=7.0,
        bump_directions=np.zeros((0, 3)),
        bump_amplitudes=[],
        bump_kappas=[],
        linear_map=lin,
        shear_coefficients=[[0.3, 0.01, 0.0], [-0.2, 0.0, 0.001]],
    )
    expected = 4.0 / 3.0 * np.pi * 7.0**3 * abs(np.linalg.det(lin))
    assert tumor_volume_mm3(shape) == pytest.approx(expected, rel=1e-13)
    # and the inside test agrees: Monte Carlo over a box holding the body
    pts_surface = shape.surface_points(64, 128)
    lo, hi = pts_surface.min(0) - 1, pts_surface.max(0) + 1
    n = 200_000
    pts = lo + (hi - lo) * rng.random((n, 3))
    frac = shape.contains(pts).mean()
    box = np.prod(hi - lo)
    sigma = box * np.sqrt(frac * (1 - frac) / n)
    assert abs(frac * box - expected) < 4 * sigma


def test_quadrature_is_converged():
    rng = np.random.default_rng(1)
    for _ in range(5):
        shape = random_tumor_shape(rng, equivalent_diameter_mm=rng.uniform(20, 45))
        v = tumor_volume_mm3(shape)
        v_fine = tumor_volume_mm3(shape, n_theta=256, n_phi=512)
        assert abs(v - v_fine) / v_fine < 1e-10


def test_random_shape_has_requested_equivalent_diameter():
    rng = np.random.default_rng(2)
    shape = random_tumor_shape(rng, equivalent_diameter_mm=33.0)
    assert tumor_volume_mm3(shape) == pytest.approx(np.pi * 33.0**3 / 6.0, rel=1e-10)


def test_volume_agrees_with_monte_carlo(small):
    shape = small.tumor_shape
    surf = shape.surface_points(64, 128)
    lo, hi = surf.min(0) - 1.0, surf.max(0) + 1.0
    rng = np.random.default_rng(3)
    n = 400_000
    pts = lo + (hi - lo) * rng.random((n, 3))
    frac = shape.contains(pts).mean()
    box = float(np.prod(hi - lo))
    sigma = box * np.sqrt(frac * (1 - frac) / n)
    assert sigma / small.true_volume_mm3 < 0.005  # the check is sharp enough for 0.5 %
    assert abs(frac * box - small.true_volume_mm3) < 4 * sigma


def test_volume_agrees_with_fine_voxel_count(small):
    # midpoint rule on a 0.3 mm lattice: error ~ surface * h^2, far below 0.2 %
    shape = small.tumor_shape
    surf = shape.surface_points(64, 128)
    h = 0.3
    axes = [
        np.arange(a, b, h) + h / 2 for a, b in zip(surf.min(0) - 1, surf.max(0) + 1, strict=True)
    ]
    pts = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    count = shape.contains(pts).sum() * h**3
    assert count == pytest.approx(small.true_volume_mm3, rel=2e-3)


def test_contains_matches_naive_reference(small):
    shape = small.tumor_shape
    rng = np.random.default_rng(4)
    surf = shape.surface_points(32, 64)
    pts = surf.min(0) - 2 + (np.ptp(surf, 0) + 4) * rng.random((50_000, 3))
    fast = shape.contains(pts)
    assert 0.1 < fast.mean() < 0.9
    np.testing.assert_array_equal(fast, _naive_inside(shape, pts))


def test_tumor_shape_copies_its_inputs():
    dirs = np.array([[1.0, 0.0, 0.0]])
    lin = np.eye(3)
    shape = TumorShape((0, 0, 0), 5.0, dirs, [0.2], [3.0], lin, np.zeros((2, 1)))
    dirs[0] = (0, 1, 0)
    lin[0, 0] = 7.0
    np.testing.assert_array_equal(shape.bump_directions, [[1.0, 0.0, 0.0]])
    assert shape.linear_map[0, 0] == 1.0


# ---------------------------------------------------------------------------
# Ground-truth masks
# ---------------------------------------------------------------------------


def test_slice_masks_are_the_inside_test_at_slice_centres(small):
    pts = _voxel_centres(small.scan.affine, small.scan.shape)
    expected = small.tumor_shape.contains(pts).reshape(small.scan.shape)
    np.testing.assert_array_equal(small.slice_masks, expected)
    np.testing.assert_array_equal(small.slice_masks, small.tissue_labels == 6)


def test_slice_riemann_sum_and_fine_mask_match_volume(small, medium):
    for p in (small, medium):
        v = p.true_volume_mm3
        slab = p.slice_masks.sum() * p.scan.pixel_area_mm2 * p.scan.slab_height_mm
        assert abs(slab - v) / v < 0.05
        fine = p.fine_mask.sum() * p.scan.pixel_area_mm2 * abs(p.fine_affine[2, 2])
        assert abs(fine - v) / v < 0.01
        # whole tumour inside the fine grid, not touching its end planes
        assert not p.fine_mask[[0, -1]].any()


def test_fine_mask_geometry(small):
    step = small.scan.slice_step_mm
    fine_step = small.fine_affine[2, 2]
    ratio = int(round(step / fine_step))
    assert small.fine_mask.shape == ((small.scan.n_slices - 1) * ratio + 1, *small.scan.shape[1:])
    np.testing.assert_array_equal(small.fine_affine[:2], small.scan.affine[:2])
    assert small.fine_affine[2, 3] == small.scan.affine[2, 3]
    # every ratio-th fine plane is an acquired slice's centre plane
    np.testing.assert_array_equal(small.fine_mask[::ratio], small.slice_masks)
    # and the fine mask is the inside test at its own voxel centres
    pts = _voxel_centres(small.fine_affine, small.fine_mask.shape)
    np.testing.assert_array_equal(small.fine_mask.ravel(), small.tumor_shape.contains(pts))


def test_cross_section_centroid_drifts(small, medium):
    for p in (small, medium):
        zs = np.flatnonzero(p.slice_masks.any(axis=(1, 2)))
        assert len(zs) >= 4
        cents = np.array([np.argwhere(p.slice_masks[k]).mean(axis=0) for k in zs])
        cents_mm = cents * np.array(p.scan.pixel_spacing_mm)
        steps = np.linalg.norm(np.diff(cents_mm, axis=0), axis=1)
        assert np.ptp(cents_mm, axis=0).max() > 3.0
        assert np.count_nonzero(steps > 0.5) >= len(steps) // 2


def test_tumour_sits_in_one_hemisphere_of_brain(small, medium):
    for p in (small, medium):
        idx = np.argwhere(p.fine_mask)[:, ::-1].astype(float)  # (x, y, z) indices
        pts = idx @ p.fine_affine[:3, :3].T + p.fine_affine[:3, 3]
        assert np.all(pts[:, 0] > 0) or np.all(pts[:, 0] < 0)
        # the pixels around every cross-section are brain tissue (CSF, GM, WM)
        ring = ndimage.binary_dilation(p.slice_masks, structure=np.ones((1, 3, 3))) & ~p.slice_masks
        assert set(np.unique(p.tissue_labels[ring])) <= {3, 4, 5}


def test_tumour_sizes_across_seeds():
    # different seeds give different tumours of 25-45 mm equivalent diameter
    # (no n_slices limit, so no shrinking)
    diam, centres = [], []
    for seed in range(4):
        p = make_phantom_patient(seed, matrix_size=(48, 48))
        d = p.params["tumor_shape"]["equivalent_diameter_mm"]
        assert d == pytest.approx((6 * p.true_volume_mm3 / np.pi) ** (1 / 3))
        assert 25.0 <= d <= 45.0
        assert p.params["tumor_shape"]["scale_factor"] == 1.0
        diam.append(d)
        centres.append(p.tumor_shape.center_mm)
    assert len(set(np.round(diam, 6))) == 4
    assert np.min(np.ptp(np.array(centres), axis=0)) > 1.0


# ---------------------------------------------------------------------------
# Determinism, normal patient
# ---------------------------------------------------------------------------


def test_same_seed_gives_identical_patient(small):
    again = make_phantom_patient(5, **SMALL)
    for name in ("slice_masks", "fine_mask", "fine_affine", "tissue_labels"):
        np.testing.assert_array_equal(getattr(again, name), getattr(small, name))
    np.testing.assert_array_equal(again.scan.image, small.scan.image)
    np.testing.assert_array_equal(again.scan.affine, small.scan.affine)
    assert again.true_volume_mm3 == small.true_volume_mm3
    assert json.dumps(again.params, sort_keys=True) == json.dumps(small.params, sort_keys=True)


def test_different_seeds_differ(small):
    other = make_phantom_patient(6, **SMALL)
    assert other.true_volume_mm3 != small.true_volume_mm3
    assert not np.array_equal(other.slice_masks, small.slice_masks)
    assert not np.array_equal(other.scan.image, small.scan.image)
    assert not np.array_equal(other.tissue_labels, small.tissue_labels)


def test_normal_patient_has_no_tumour(small):
    normal = make_phantom_patient(5, tumor=False, **SMALL)
    assert normal.true_volume_mm3 == 0.0
    assert normal.tumor_shape is None
    assert not normal.slice_masks.any() and not normal.fine_mask.any()
    assert normal.slice_masks.shape == small.slice_masks.shape
    assert normal.fine_mask.shape == small.fine_mask.shape
    assert not np.any(normal.tissue_labels == 6)
    # same head as the abnormal patient of the same seed, away from the tumour
    away = ~small.slice_masks
    np.testing.assert_array_equal(normal.tissue_labels[away], small.tissue_labels[away])
    json.dumps(normal.params)


def test_outputs_are_read_only(small):
    for arr in (
        small.scan.image,
        small.slice_masks,
        small.fine_mask,
        small.tissue_labels,
        small.fine_affine,
    ):
        with pytest.raises(ValueError, match="read-only"):
            arr[(0,) * arr.ndim] = 1


# ---------------------------------------------------------------------------
# Head anatomy and image formation
# ---------------------------------------------------------------------------


def _interior_means(p: PhantomPatient) -> dict[int, float]:
    """Mean intensity per label over pixels whose 3x3 in-plane neighbourhood
    (and the slices' labels) are uniform, i.e. free of partial volume."""
    out = {}
    for lab in (3, 4, 5, 6):
        m = p.tissue_labels == lab
        core = ndimage.binary_erosion(m, structure=np.ones((1, 3, 3)))
        assert core.sum() > 20, lab
        out[lab] = float(p.scan.image[core].mean())
    return out


@pytest.mark.parametrize("modality", ["t2", "flair"])
def test_tissue_intensity_order(medium, modality):
    p = (
        medium
        if modality == "t2"
        else make_phantom_patient(11, matrix_size=(128, 128), modality="flair")
    )
    mean = _interior_means(p)
    sigma = p.params["noise_sigma"]
    csf, gm, wm, tum = mean[3], mean[4], mean[5], mean[6]
    if modality == "t2":
        assert wm < gm < tum < csf
        # distinct histogram modes: gaps of several noise standard deviations
        assert min(gm - wm, tum - gm, csf - tum) > 3 * sigma
    else:
        assert csf < wm < gm < tum
        assert tum == max(mean.values()) and csf == min(mean.values())
        assert min(wm - csf, gm - wm, tum - gm) > 3 * sigma
    # nominal contrast survives the +-15 % bias field
    nominal = TISSUE_INTENSITIES[modality]
    for lab, value in mean.items():
        assert value == pytest.approx(nominal[lab], rel=0.2)


def test_noise_is_rician():
    p = make_phantom_patient(7, matrix_size=(96, 96), n_slices=6, noise_fraction=0.05)
    img = p.scan.image
    assert img.dtype == np.float32
    assert img.min() >= 0.0
    sigma = p.params["noise_sigma"]
    assert sigma == pytest.approx(0.05 * p.params["noise_free_max"], rel=1e-12)
    # background: pure Rayleigh, mean sigma sqrt(pi/2), variance (2 - pi/2) sigma^2
    bg = ndimage.binary_erosion(p.tissue_labels == 0, structure=np.ones((3, 3, 3)))
    vals = img[bg].astype(float)
    assert vals.size > 10_000
    assert vals.mean() == pytest.approx(sigma * np.sqrt(np.pi / 2), rel=0.03)
    assert vals.var() == pytest.approx((2 - np.pi / 2) * sigma**2, rel=0.06)
    # noise-free option: background exactly zero
    clean = make_phantom_patient(7, matrix_size=(96, 96), n_slices=6, noise_fraction=0.0)
    assert np.all(clean.scan.image[bg] == 0.0)


def test_partial_volume_edges(small):
    # pixels straddling a boundary take intermediate values: noise-free images of the
    # scalp (600) / background (0) border contain values strictly in between
    clean = make_phantom_patient(5, **SMALL, noise_fraction=0.0, bias_field_strength=0.0)
    values = np.unique(np.round(clean.scan.image, 3))
    assert np.count_nonzero((values > 1) & (values < 599) & ~np.isin(values, [50, 300, 450])) > 50
    # pure interior pixels carry exactly the nominal intensity
    wm_core = ndimage.binary_erosion(clean.tissue_labels == 5, structure=np.ones((3, 3, 3)))
    np.testing.assert_allclose(clean.scan.image[wm_core], 300.0, rtol=1e-6)


def test_skull_separates_brain_from_scalp(small, medium):
    four = ndimage.generate_binary_structure(2, 1)[None]  # in-plane 4-neighbourhood
    for p in (small, medium):
        brain = np.isin(p.tissue_labels, [3, 4, 5, 6])
        scalp_or_air = np.isin(p.tissue_labels, [0, 1])
        near_scalp = ndimage.binary_dilation(scalp_or_air, structure=four)
        assert not (brain & near_scalp).any()
        # every slice holding brain has skull around it
        for k in np.flatnonzero(brain.any(axis=(1, 2))):
            assert (p.tissue_labels[k] == 2).any()


def test_adaptive_rendering_equals_full_supersampling(small):
    # the renderer skips the supersampling of provably uniform pixels; compare it
    # with the naive renderer that supersamples every pixel
    p = small
    head = _random_head(np.random.default_rng(0))
    shape = p.tumor_shape
    tum, dirs, amps, kappas = shape._packed()
    surf = shape.surface_points(64, 128)
    bbox = np.concatenate([surf.min(0) - 2, surf.max(0) + 2])
    aff = p.scan.affine.copy()
    values = np.array(TISSUE_INTENSITIES["t2"])
    sub_xy = (np.arange(3) + 0.5) / 3 - 0.5
    sub_z = ((np.arange(4) + 0.5) / 4 - 0.5) * 0.4
    args = (
        aff,
        *p.scan.shape,
        sub_xy,
        sub_z,
        head.packed(),
        head.wob_h,
        head.wob_b,
        head.ventricles,
        tum,
        dirs,
        amps,
        kappas,
        bbox,
        values,
    )
    fast_img, fast_lab = _render(*args, True)
    full_img, full_lab = _render(*args, False)
    np.testing.assert_array_equal(fast_lab, full_lab)
    np.testing.assert_allclose(fast_img, full_img, rtol=1e-12, atol=1e-9)
    assert 0 < np.count_nonzero(fast_img != values[fast_lab])  # some mixed pixels exist


def test_head_fields_match_monomial_definition_and_lipschitz_bound():
    head = _random_head(np.random.default_rng(9))
    packed = head.packed()
    rng = np.random.default_rng(10)
    pts = rng.uniform(-110, 110, size=(20_000, 3))
    got = _head_fields_many(pts, packed, head.wob_h, head.wob_b)
    q = pts / head.semi_axes
    n = np.linalg.norm(q, axis=1, keepdims=True)
    qp = q * np.minimum(1.0, 1.2 / n)
    mono = np.prod(qp[:, None, :] ** _MONOMIALS[None], axis=-1)
    rho_h = n[:, 0] - mono @ head.wob_h
    rho_b = rho_h - mono @ head.wob_b
    np.testing.assert_allclose(got[:, 0], rho_h, atol=1e-12)
    np.testing.assert_allclose(got[:, 1], rho_b, atol=1e-12)
    # the renderer's Lipschitz bounds hold (finite differences along random directions)
    d = rng.normal(size=pts.shape)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    h = 0.05
    moved = _head_fields_many(pts + h * d, packed, head.wob_h, head.wob_b)
    slope = np.abs(moved - got) / h
    assert slope[:, 0].max() <= packed[11]
    assert slope[:, 1].max() <= packed[12]


# ---------------------------------------------------------------------------
# Presets, geometry, parameters
# ---------------------------------------------------------------------------


def test_default_preset_smoke():
    p = make_phantom_patient(0)
    scan = p.scan
    assert scan.shape[1:] == (256, 256)
    assert 28 <= scan.n_slices <= 31
    assert scan.pixel_spacing_mm == (0.9375, 0.9375)
    assert (scan.slice_thickness_mm, scan.slice_gap_mm, scan.slice_step_mm) == (2.0, 3.0, 5.0)
    assert scan.slab_height_mm == 5.0
    assert scan.modality == "t2" and scan.patient_id == "phantom-0"
    assert scan.source.startswith("synthetic phantom seed=0")
    assert scan.source_grid.shape == (256, 256, scan.n_slices)
    np.testing.assert_array_equal(scan.source_grid.affine, scan.affine)
    # radiological axial: columns -> left (R decreases), rows -> posterior, slices -> superior
    assert scan.affine[0, 0] == -0.9375 and scan.affine[1, 1] == -0.9375
    assert scan.affine[2, 2] == 5.0
    # RAS origin near the head centre
    head = np.argwhere(p.tissue_labels > 0)
    centre = scan.index_to_ras(head.mean(axis=0))
    assert np.all(np.abs(centre) < 8.0)
    assert scan.image.min() >= 0 and scan.image.dtype == np.float32
    zs = np.flatnonzero(p.slice_masks.any(axis=(1, 2)))
    assert 5 <= len(zs) <= 10
    assert np.all(np.diff(zs) == 1)
    assert abs(p.fine_mask.sum() * 0.9375**2 * 0.5 - p.true_volume_mm3) < 0.005 * p.true_volume_mm3
    json.dumps(p.params)


def test_paper_preset_geometry():
    # the paper preset's 480 x 640 grid at 0.45 mm; a coarser spacing keeps its FOV
    p = make_phantom_patient(1, preset="paper", pixel_spacing_mm=1.8, n_slices=8)
    assert p.scan.shape == (8, 120, 160)
    assert p.params["matrix_size_rows_cols"] == [120, 160]
    q = make_phantom_patient(1, preset="paper", matrix_size=(96, 128), n_slices=8)
    assert q.scan.pixel_spacing_mm == (2.25, 2.25)


def test_overrides_scale_everything():
    p = make_phantom_patient(
        2,
        matrix_size=(64, 80),
        pixel_spacing_mm=3.5,
        n_slices=12,
        slice_thickness_mm=3.0,
        slice_gap_mm=1.0,
        modality="flair",
        patient_id="case_A-1",
    )
    assert p.scan.shape == (12, 64, 80)
    assert p.scan.slice_step_mm == 4.0 and p.scan.slice_gap_mm == 1.0
    assert p.scan.modality == "flair" and p.scan.patient_id == "case_A-1"
    assert p.fine_mask.shape == (int(11 * 4.0 / 0.5) + 1, 64, 80)
    assert p.fine_mask.any() and not p.fine_mask[[0, -1]].any()


def test_short_coverage_shrinks_tumour_to_fit():
    p = make_phantom_patient(4, matrix_size=(64, 64), n_slices=6)  # 25 mm between end slices
    info = p.params["tumor_shape"]
    assert info["scale_factor"] < 1.0
    assert p.fine_mask.any() and not p.fine_mask[[0, -1]].any()
    assert p.true_volume_mm3 == pytest.approx(
        np.pi / 6 * (info["target_equivalent_diameter_mm"] * info["scale_factor"]) ** 3, rel=1e-9
    )


# ---------------------------------------------------------------------------
# Validation: one test per branch
# ---------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"seed": -1}, "seed must be a non-negative integer"),
        ({"seed": 1.5}, "seed must be a non-negative integer"),
        ({"preset": "huge"}, "preset must be one of"),
        ({"modality": "t1"}, "modality must be one of"),
        ({"tumor": "yes"}, "tumor must be True or False"),
        ({"patient_id": "../x"}, "unsafe patient id"),
        ({"matrix_size": (4, 96)}, "matrix_size must be two integers"),
        ({"matrix_size": 96}, "matrix_size must be two integers"),
        ({"pixel_spacing_mm": 0.0}, "pixel_spacing_mm must be a positive number of mm"),
        ({"matrix_size": (64, 64), "pixel_spacing_mm": 1.0}, "field of view .* too small"),
        ({"slice_thickness_mm": -2.0}, "slice_thickness_mm must be a positive number of mm"),
        ({"slice_gap_mm": float("nan")}, "slice_gap_mm must be a non-negative number of mm"),
        ({"noise_fraction": 1.0}, "noise_fraction must be < 1"),
        ({"noise_fraction": -0.1}, "noise_fraction must be a non-negative number"),
        ({"bias_field_strength": 0.95}, "bias_field_strength must be <= 0.9"),
        ({"fine_step_mm": 0.0}, "fine_step_mm must be a positive number of mm"),
        ({"inplane_subsamples": 0}, "inplane_subsamples must be an integer >= 1"),
        ({"n_slices": 0}, "n_slices must be an integer >= 1"),
        ({"n_slices": 1}, "too little of the brain to hold a tumour"),
    ],
)
def test_make_phantom_patient_rejects_bad_input(kwargs, match):
    args = {"seed": 0, "matrix_size": (48, 48), **kwargs}
    seed = args.pop("seed")
    with pytest.raises(InputError, match=match):
        make_phantom_patient(seed, **args)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"pixel_spacing_mm": "big"}, "pixel_spacing_mm must be a positive number of mm"),
        ({"slab_subsamples": 2.0}, "slab_subsamples must be an integer >= 1"),
    ],
)
def test_make_phantom_patient_rejects_wrong_types_with_type_error(kwargs, match):
    with pytest.raises(TypeError, match=match):
        make_phantom_patient(0, matrix_size=(48, 48), **kwargs)


def test_one_slice_normal_patient_is_allowed():
    p = make_phantom_patient(0, matrix_size=(48, 48), n_slices=1, tumor=False)
    assert p.scan.shape == (1, 48, 48) and p.fine_mask.shape == (1, 48, 48)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"center_mm": (0, 0)}, "center_mm must be 3 finite numbers"),
        ({"radius_mm": 0.0}, "radius_mm must be a positive number"),
        ({"bump_amplitudes": [0.1, 0.2]}, "must have the same length"),
        ({"bump_directions": [[0, 0, 0]]}, "finite non-zero vectors"),
        ({"bump_kappas": [np.inf]}, "must be finite"),
        ({"bump_kappas": [-1.0]}, "bump_kappas must be >= 0"),
        ({"bump_amplitudes": [-1.0]}, "must sum to more than -1"),
        ({"linear_map": np.ones((2, 2))}, "linear_map must be a finite 3x3 matrix"),
        ({"linear_map": np.zeros((3, 3))}, "linear_map must be invertible"),
        ({"shear_coefficients": np.zeros(3)}, r"shear_coefficients must be a finite \(2, k\)"),
        ({"shear_coefficients": np.ones((2, 4))}, "above degree 3 are not supported"),
    ],
)
def test_tumor_shape_rejects_bad_input(kwargs, match):
    args = {
        "center_mm": (0, 0, 0),
        "radius_mm": 5.0,
        "bump_directions": [[1, 0, 0]],
        "bump_amplitudes": [0.2],
        "bump_kappas": [3.0],
        "linear_map": np.eye(3),
        "shear_coefficients": np.zeros((2, 1)),
        **kwargs,
    }
    with pytest.raises(InputError, match=match):
        TumorShape(**args)


def test_tumor_volume_rejects_bad_input():
    with pytest.raises(InputError, match="shape must be a TumorShape"):
        tumor_volume_mm3("ball")
    with pytest.raises(InputError, match="need n_theta >= 2 and n_phi >= 3"):
        tumor_volume_mm3(TumorShape.sphere((0, 0, 0), 1.0), n_theta=1)


def test_random_tumor_shape_rejects_bad_input():
    with pytest.raises(InputError, match="equivalent_diameter_mm must be positive"):
        random_tumor_shape(np.random.default_rng(0), equivalent_diameter_mm=-3.0)
    with pytest.raises(InputError, match="rng must be a numpy.random.Generator"):
        random_tumor_shape(0, equivalent_diameter_mm=30.0)


def test_wobble_gradients_and_hessian_bounds_hold_against_finite_differences():
    from tumor3d.phantom.raster import _wobble_gradients

    head = _random_head(np.random.default_rng(9))
    packed = head.packed()
    rng = np.random.default_rng(11)
    q = rng.normal(size=(2_000, 3))
    q *= rng.uniform(0.0, 1.15, size=(len(q), 1)) / np.linalg.norm(q, axis=1, keepdims=True)

    def wob(coef, pts):  # the monomial definition, inside the ball (no projection)
        return np.prod(pts[:, None, :] ** _MONOMIALS[None], axis=-1) @ coef

    h = 1e-5
    for t, coef in enumerate((head.wob_h, head.wob_b)):
        got = np.array([_wobble_gradients(*p, head.wob_h, head.wob_b) for p in q])[:, 3 * t :]
        for r in range(3):
            e = np.zeros(3)
            e[r] = h
            fd = (wob(coef, q + e) - wob(coef, q - e)) / (2 * h)
            np.testing.assert_allclose(got[:, r], fd, atol=1e-8)  # gh, then gb
    # the Hessian bounds (packed [13], [14]): second differences along random directions
    d = rng.normal(size=q.shape)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    h = 0.02
    for coef, bound in ((head.wob_h, packed[13]), (head.wob_h + head.wob_b, packed[14])):
        second = np.abs(wob(coef, q + h * d) - 2 * wob(coef, q) + wob(coef, q - h * d)) / h**2
        assert 0 < second.max() <= bound


def test_a_box_that_a_head_field_crosses_is_never_called_pure():
    # the renderer skips a pixel's samples when _fields_pure_near bounds the fields over
    # its box; put a threshold at a value the box does reach and it must refuse
    from tumor3d.phantom.raster import _fields_pure_near

    head = _random_head(np.random.default_rng(9))
    packed = head.packed()
    far = packed.copy()
    far[6:11] = 50.0  # every threshold out of reach
    rng = np.random.default_rng(12)
    n_box = 400
    u = rng.normal(size=(n_box, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    centres = u * rng.uniform(0.8, 1.05, size=(n_box, 1)) * head.semi_axes
    boxes = rng.uniform(0.2, 2.5, size=(n_box, 3))
    corners = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
    judged = 0
    for c, b in zip(centres, boxes, strict=True):
        offsets = np.vstack([corners, rng.uniform(-1, 1, size=(56, 3))]) * b
        rho0 = _head_fields_many(c[None], packed, head.wob_h, head.wob_b)[0]
        rho = _head_fields_many(c + offsets, packed, head.wob_h, head.wob_b)
        judged += _fields_pure_near(*c, *rho0, b, far, head.wob_h, head.wob_b)
        for f in range(2):  # rho_h (threshold 6), rho_b (threshold 9)
            crossed = far.copy()
            crossed[6 + 3 * f] = rho[np.argmax(np.abs(rho[:, f] - rho0[f])), f]
            assert not _fields_pure_near(*c, *rho0, b, crossed, head.wob_h, head.wob_b)
    assert judged > 0.9 * n_box  # boxes were judged by the bound, not refused outright
