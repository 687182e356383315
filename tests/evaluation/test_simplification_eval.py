"""Tests of tumor3d.evaluation.simplification (Eq. 11, surface distances, quality)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.evaluation.simplification import (
    sample_surface,
    simplification_rows,
    surface_distances,
    triangle_quality,
    vertex_hausdorff,
    volume_change_percent,
)
from tumor3d.geometry.mesh import Mesh
from tumor3d.geometry.surface import extract_surface, mesh_area_mm2
from tumor3d.simplify import simplify_mesh


def _ball(radius_vox=8.0):
    n = int(2 * radius_vox) + 6
    c = (n - 1) / 2 + 0.2
    z, y, x = np.ogrid[:n, :n, :n]
    mask = (z - c) ** 2 + (y - c) ** 2 + (x - c) ** 2 <= radius_vox**2
    return extract_surface(mask, np.diag([1.0, 1.0, 1.2, 1.0]))


def _octahedron(r):
    v = r * np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], float)
    f = np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4],
                  [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]])  # fmt: skip
    return Mesh(v, f)


@pytest.fixture(scope="module")
def ball():
    return _ball()


def test_vertex_hausdorff_matches_brute_force(ball):
    rng = np.random.default_rng(1)
    other = Mesh(ball.vertices + rng.normal(0, 0.3, ball.vertices.shape), ball.faces)
    d = np.linalg.norm(ball.vertices[:, None] - other.vertices[None], axis=2)
    out = vertex_hausdorff(ball, other)
    assert out["d_ab_mm"] == pytest.approx(d.min(axis=1).max())
    assert out["d_ba_mm"] == pytest.approx(d.min(axis=0).max())
    assert out["shd_vertex_mm"] == max(out["d_ab_mm"], out["d_ba_mm"])


def test_eq11_second_term_is_zero_for_the_papers_method(ball):
    # [A28]: the curvature method keeps vertices in place, V(M2) subset V(M1)
    out = simplify_mesh(ball, method="curvature", reduction_percent=60.0)
    shd = vertex_hausdorff(ball, out)
    assert shd["d_ba_mm"] == 0.0
    assert shd["d_ab_mm"] > 0.0
    qem = simplify_mesh(ball, method="qem", reduction_percent=60.0)
    assert vertex_hausdorff(ball, qem)["d_ba_mm"] > 0.0


def test_surface_distance_between_concentric_octahedra():
    # octahedra |x|+|y|+|z| = r: the distance between the parallel faces is (R - r) / sqrt(3)
    inner, outer = _octahedron(10.0), _octahedron(12.0)
    d = surface_distances(inner, outer, n_samples=5000)
    gap = 2.0 / math.sqrt(3.0)
    assert d["d_ab_max_mm"] == pytest.approx(gap, rel=1e-4)  # every inner point is on a face
    assert d["d_ab_mean_mm"] == pytest.approx(gap, rel=1e-4)
    assert d["d_ba_max_mm"] == pytest.approx(2.0, rel=1e-4)  # outer apex to inner apex
    assert gap < d["d_ba_mean_mm"] < 2.0
    assert d["hausdorff_mm"] == pytest.approx(2.0, rel=1e-4)
    assert d["mean_distance_mm"] == pytest.approx(0.5 * (d["d_ab_mean_mm"] + d["d_ba_mean_mm"]))


def test_surface_distance_of_a_mesh_to_itself_is_zero(ball):
    d = surface_distances(ball, ball, n_samples=2000)
    assert d["hausdorff_mm"] < 1e-4


def test_surface_hausdorff_sees_what_eq11_misses(ball):
    # a pure re-triangulation with the same vertices but fewer of them can look
    # perfect to Eq. 11's second term while the surface moved
    out = simplify_mesh(ball, method="curvature", reduction_percent=80.0)
    assert surface_distances(ball, out)["hausdorff_mm"] > 0.0


def test_sample_surface_is_area_uniform_and_on_the_surface():
    mesh = _octahedron(3.0)
    pts = sample_surface(mesh, 20000, seed=3)
    np.testing.assert_allclose(np.abs(pts).sum(axis=1), 3.0, atol=1e-9)
    # each of the 8 equal faces gets 1/8 of the samples
    octant = (pts[:, 0] > 0) * 4 + (pts[:, 1] > 0) * 2 + (pts[:, 2] > 0)
    counts = np.bincount(octant, minlength=8)
    assert np.all(np.abs(counts / 20000 - 1 / 8) < 0.01)
    np.testing.assert_array_equal(pts, sample_surface(mesh, 20000, seed=3))


def test_volume_change_of_a_scaled_mesh(ball):
    bigger = Mesh(ball.vertices * 2.0, ball.faces)
    assert volume_change_percent(ball, bigger) == pytest.approx(700.0)
    assert volume_change_percent(ball, ball) == 0.0


def test_triangle_quality_of_known_triangles():
    eq = Mesh(np.array([[0, 0, 0], [1, 0, 0], [0.5, math.sqrt(3) / 2, 0]]), np.array([[0, 1, 2]]))
    q = triangle_quality(eq)
    assert q["quality_min"] == pytest.approx(1.0)
    assert q["min_angle_deg"] == pytest.approx(60.0)
    right = Mesh(np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float), np.array([[0, 1, 2]]))
    q = triangle_quality(right)
    assert q["quality_mean"] == pytest.approx(4 * math.sqrt(3) * 0.5 / 4)
    assert q["min_angle_deg"] == pytest.approx(45.0)
    assert q["fraction_quality_below_0_3"] == 0.0


def test_simplification_rows(ball):
    rows = simplification_rows(ball, case="ball", methods=("curvature", "memoryless"),
                               reduction_percents=(50.0,), n_samples=2000)  # fmt: skip
    assert [(r["method"], r["reduction_percent"]) for r in rows] == [
        ("curvature", 50.0),
        ("memoryless", 50.0),
    ]
    for r in rows:
        assert r["case"] == "ball" and r["watertight"] is True
        assert r["faces_out"] <= r["faces_target"]
        assert r["n_nonmanifold_edges"] == 0 == r["n_boundary_edges"]
        assert 0 < r["hausdorff_mm"] and 0 < r["mean_distance_mm"] < r["hausdorff_mm"]
        assert 0 < r["quality_mean"] <= 1
    assert rows[0]["d_ba_mm"] == 0.0
    assert abs(rows[1]["volume_change_percent"]) < 1e-9
    assert mesh_area_mm2(ball) > 0


@pytest.mark.parametrize(
    ("call", "match"),
    [
        (lambda m: vertex_hausdorff("x", m), "mesh_a must be a tumor3d.geometry.mesh.Mesh"),
        (lambda m: surface_distances(m, Mesh(np.zeros((0, 3)), np.zeros((0, 3), int))), "empty"),
        (lambda m: sample_surface(m, -1), "n_samples"),
        (lambda m: sample_surface(m, 2.5), "n_samples"),
        (lambda m: simplification_rows(m, case=3), "case"),
    ],
)
def test_validation(ball, call, match):
    with pytest.raises(InputError, match=match):
        call(ball)
