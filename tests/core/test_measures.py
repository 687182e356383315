import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.geometry.measures import (
    cavalieri_alpha,
    cavalieri_precision,
    max_diameter_mm,
    rano_diameters,
)
from tumor3d.metrics import volume_eq7_mm3
from tumor3d.phantom import TumorShape, random_tumor_shape

# ----------------------------------------------------------------- Cavalieri


def test_alpha_matches_gundersen_jensen_constants_and_is_continuous():
    assert cavalieri_alpha(0.0) == pytest.approx(1 / 12, rel=1e-12)
    assert cavalieri_alpha(1.0) == pytest.approx(1 / 240, rel=1e-12)
    # q = 1/2 is a removable singularity: the value is the limit of its neighbours
    a = [cavalieri_alpha(q) for q in (0.49, 0.5, 0.51)]
    assert a[0] > a[1] > a[2]
    assert a[1] == pytest.approx(0.5 * (a[0] + a[2]), rel=1e-3)


def _area_function(shape: TumorShape, z_mm: np.ndarray, step_mm: float = 0.4) -> np.ndarray:
    """Cross-section areas (mm2) of a phantom tumour at heights z (RAS S), by fine sampling."""
    pts = shape.surface_points(24, 48)
    lo, hi = pts.min(axis=0) - 1.0, pts.max(axis=0) + 1.0
    xs = np.arange(lo[0], hi[0], step_mm)
    ys = np.arange(lo[1], hi[1], step_mm)
    gx, gy = np.meshgrid(xs, ys, indexing="xy")
    areas = np.empty(len(z_mm))
    for i, z in enumerate(z_mm):
        p = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], axis=1)
        areas[i] = shape.contains(p).sum() * step_mm**2
    return areas


def _phase_spread(area_of_z, z_lo, z_hi, slab_mm, n_phases, rng):
    """Eq. 7 volumes over random slice phases, and the mean predicted variance."""
    volumes, predicted = [], []
    for _ in range(n_phases):
        z = np.arange(z_lo + rng.uniform(0, slab_mm), z_hi, slab_mm)
        areas = area_of_z(z)
        p = cavalieri_precision(areas, slab_mm)
        volumes.append(p.volume_mm3)
        predicted.append(p.variance_mm6)
    return np.asarray(volumes), float(np.mean(predicted))


@pytest.mark.parametrize("slab_mm", [3.0, 5.0, 7.0])
def test_predicted_error_matches_phase_spread_on_an_ellipsoid(slab_mm):
    # Exact area function A(z) = pi a b (1 - z^2/c^2): no rasterisation noise.
    a, b, c = 20.0, 15.0, 18.0
    truth = 4.0 / 3.0 * np.pi * a * b * c

    def area(z):
        return np.where(np.abs(z) < c, np.pi * a * b * (1 - z**2 / c**2), 0.0)

    rng = np.random.default_rng(1)
    volumes, var = _phase_spread(area, -c - slab_mm, c + slab_mm, slab_mm, 3000, rng)
    assert volumes.mean() == pytest.approx(truth, rel=2e-3)  # Cavalieri is unbiased
    ratio = np.sqrt(var) / volumes.std()
    # Stated tolerance: the predicted standard error within [0.6, 1.5] x the observed spread.
    assert 0.6 <= ratio <= 1.5, ratio


def test_predicted_error_matches_phase_spread_on_random_phantom_tumours():
    rng = np.random.default_rng(7)
    ratios = []
    for _ in range(3):
        shape = random_tumor_shape(rng, equivalent_diameter_mm=float(rng.uniform(25, 40)))
        pts = shape.surface_points(24, 48)
        z_lo, z_hi = pts[:, 2].min() - 1.0, pts[:, 2].max() + 1.0
        fine_z = np.arange(z_lo - 6.0, z_hi + 6.0, 0.1)
        fine_a = _area_function(shape, fine_z)

        def area(z, fine_z=fine_z, fine_a=fine_a):
            return np.interp(z, fine_z, fine_a, left=0.0, right=0.0)

        volumes, var = _phase_spread(area, z_lo - 5.0, z_hi + 5.0, 5.0, 1500, rng)
        ratios.append(np.sqrt(var) / volumes.std())
    ratios = np.asarray(ratios)
    # Same stated tolerance, on irregular, sheared shapes sampled every 5 mm.
    assert np.all((ratios >= 0.5) & (ratios <= 2.0)), ratios


def test_cavalieri_volume_is_eq7_and_interval_brackets_it():
    counts = np.array([0, 40, 90, 120, 70, 10, 0])
    p = cavalieri_precision(counts * 0.25, 5.0)
    eq7 = volume_eq7_mm3(counts, counts > 0, pixel_area_mm2=0.25, slab_height_mm=5.0)
    assert p.volume_mm3 == pytest.approx(eq7)
    assert p.ci95_low_mm3 < p.volume_mm3 < p.ci95_high_mm3
    # the normal 95 % interval of the predicted error, z from scipy, not the module's constant
    from scipy.stats import norm

    z = norm.ppf(0.975)
    assert p.ci95_high_mm3 == pytest.approx(p.volume_mm3 * (1 + z * p.ce), rel=1e-6)
    assert p.ci95_low_mm3 == pytest.approx(p.volume_mm3 * (1 - z * p.ce), rel=1e-6)
    assert p.n_sections == 5
    q0 = cavalieri_precision(counts * 0.25, 5.0, smoothness=0.0)
    assert q0.ce == pytest.approx(p.ce * np.sqrt(240 / 12))  # variance scales with alpha


def test_cavalieri_empty_and_bad_input():
    p = cavalieri_precision(np.zeros(5), 5.0)
    assert p.volume_mm3 == 0 and p.ce == 0 and p.n_sections == 0
    with pytest.raises(InputError, match="areas_mm2 must be >= 0"):
        cavalieri_precision([1.0, -1.0], 5.0)
    with pytest.raises(InputError, match="1-D"):
        cavalieri_precision(np.ones((2, 2)), 5.0)
    with pytest.raises(InputError, match="slab_height_mm"):
        cavalieri_precision([1.0], 0.0)
    with pytest.raises(InputError, match="smoothness"):
        cavalieri_precision([1.0], 5.0, smoothness=2.0)


# ----------------------------------------------------------------- diameters


def _ellipse(shape, centre, semi_yx_px, angle_deg=0.0):
    yy, xx = np.mgrid[: shape[0], : shape[1]]
    t = np.deg2rad(angle_deg)
    y, x = yy - centre[0], xx - centre[1]
    u = y * np.cos(t) - x * np.sin(t)
    w = y * np.sin(t) + x * np.cos(t)
    return (u / semi_yx_px[0]) ** 2 + (w / semi_yx_px[1]) ** 2 <= 1


@pytest.mark.parametrize("angle", [0.0, 30.0, 75.0])
def test_rano_diameters_of_an_ellipse_within_a_pixel(angle):
    m = np.zeros((3, 200, 200), bool)
    m[0] = _ellipse((200, 200), (100, 100), (10, 20))  # a smaller slice
    m[1] = _ellipse((200, 200), (100, 100), (25, 70), angle)
    r = rano_diameters(m, (1.0, 1.0))
    assert r.slice_index == 1
    assert abs(r.longest_diameter_mm - 140.0) <= 1.5
    assert abs(r.perpendicular_diameter_mm - 50.0) <= 1.5
    assert r.product_mm2 == pytest.approx(r.longest_diameter_mm * r.perpendicular_diameter_mm)


def test_rano_diameters_use_anisotropic_pixel_spacing():
    m = _ellipse((200, 200), (100, 100), (30, 60))[None]  # 60 px tall, 120 px wide
    r = rano_diameters(m, (0.5, 1.0))  # dy = 0.5 mm, dx = 1 mm: 30 mm x 120 mm
    assert abs(r.longest_diameter_mm - 120.0) <= 1.5
    assert abs(r.perpendicular_diameter_mm - 30.0) <= 1.0


def test_rano_empty_and_bad_input():
    r = rano_diameters(np.zeros((2, 5, 5), bool), (1.0, 1.0))
    assert r.slice_index == -1 and r.longest_diameter_mm == 0.0
    with pytest.raises(InputError, match="binary"):
        rano_diameters(np.full((1, 3, 3), 2), (1.0, 1.0))
    with pytest.raises(InputError, match="3-D"):
        rano_diameters(np.zeros((3, 3), bool), (1.0, 1.0))
    with pytest.raises(InputError, match="pixel_spacing_mm"):
        rano_diameters(np.zeros((1, 3, 3), bool), (0.0, 1.0))


def test_max_diameter_matches_naive_pairwise_maximum():
    rng = np.random.default_rng(3)
    pts = rng.normal(size=(600, 3)) * np.array([10.0, 4.0, 2.0])
    naive = np.sqrt(((pts[:, None] - pts[None]) ** 2).sum(-1)).max()
    assert max_diameter_mm(pts) == pytest.approx(naive, rel=1e-12)
    # points on a sphere of radius 12: diameter 24 (to the sampling)
    u = rng.normal(size=(4000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    assert max_diameter_mm(12.0 * u) == pytest.approx(24.0, abs=0.05)
    assert max_diameter_mm(np.zeros((1, 3))) == 0.0
    with pytest.raises(InputError, match=r"\(n, 3\)"):
        max_diameter_mm(np.zeros((4, 2)))
