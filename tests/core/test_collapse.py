"""Tests of the collapse engine and the two simplifiers on it (curvature, memoryless)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tumor3d.errors import InputError
from tumor3d.geometry.mesh import Mesh
from tumor3d.geometry.surface import (
    edge_manifold_report,
    extract_surface,
    is_watertight,
    mesh_volume_mm3,
)
from tumor3d.simplify import simplify_mesh, target_face_count
from tumor3d.simplify.curvature import simplify_curvature, vertex_curvatures
from tumor3d.simplify.memoryless import simplify_memoryless

# ---------------------------------------------------------------------------
# meshes
# ---------------------------------------------------------------------------


def _icosphere(radius: float, subdivisions: int) -> Mesh:
    t = (1 + 5**0.5) / 2
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t),
         (0, -1, -t), (0, 1, -t), (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]  # fmt: skip
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4),
         (11, 10, 2), (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8),
         (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]  # fmt: skip
    verts = [np.array(p, float) / np.linalg.norm(p) for p in v]
    faces = list(f)
    for _ in range(subdivisions):
        cache: dict[tuple[int, int], int] = {}

        def mid(a, b, cache=cache):
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]

        new = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            new += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = new
    mesh = Mesh(np.array(verts) * radius, np.array(faces))
    if mesh_volume_mm3(mesh) < 0:
        mesh = Mesh(mesh.vertices, mesh.faces[:, ::-1])
    return mesh


def _ball_mask(radii_vox, spacing_zyx=(1.0, 1.0, 1.0)):
    n = [int(2 * r) + 6 for r in radii_vox]
    c = [(k - 1) / 2 for k in n]
    z, y, x = np.ogrid[: n[0], : n[1], : n[2]]
    inside = ((z - c[0]) / radii_vox[0]) ** 2 + ((y - c[1]) / radii_vox[1]) ** 2 + (
        (x - c[2]) / radii_vox[2]
    ) ** 2 <= 1.0
    dz, dy, dx = spacing_zyx
    return inside, np.diag([dx, dy, dz, 1.0])


@pytest.fixture(scope="module")
def ellipsoid():
    mask, affine = _ball_mask((9.0, 12.0, 10.0), (1.2, 0.9, 1.0))
    return extract_surface(mask, affine)


def _blob_mesh(seed: int) -> Mesh:
    """Union of a few random balls: irregular, multi-lobed, possibly several components."""
    rng = np.random.default_rng(seed)
    n = 28
    z, y, x = np.ogrid[:n, :n, :n]
    mask = np.zeros((n, n, n), bool)
    for _ in range(int(rng.integers(2, 6))):
        c = rng.uniform(7, n - 7, 3)
        r = rng.uniform(2.5, 6.5)
        mask |= (z - c[0]) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2 <= r * r
    mask |= rng.random((n, n, n)) < 0.002  # isolated voxels: octahedra
    return extract_surface(mask, np.diag([0.9, 0.9, 1.5, 1.0]))


def _euler(mesh: Mesh) -> int:
    r = edge_manifold_report(mesh)
    used = np.unique(mesh.faces).size
    return used - r["n_edges"] + r["n_faces"]


def _vertex_manifold(mesh: Mesh) -> bool:
    """Naive check: the faces around every vertex form one closed fan."""
    nxt: dict[int, dict[int, int]] = {}
    for a, b, c in mesh.faces.tolist():
        for v, p, q in ((a, b, c), (b, c, a), (c, a, b)):
            d = nxt.setdefault(v, {})
            if p in d:
                return False
            d[p] = q
    for d in nxt.values():
        start = next(iter(d))
        cur, steps = d[start], 1
        while cur != start:
            if cur not in d:
                return False
            cur = d[cur]
            steps += 1
        if steps != len(d):
            return False
    return True


# ---------------------------------------------------------------------------
# discrete curvature [Dyn01]
# ---------------------------------------------------------------------------


def test_icosphere_curvature_matches_the_spec_sanity_check():
    # spec section 6: an icosphere of radius 2 gives mean K = 0.250, H = 0.500, R = 0.500
    kh = vertex_curvatures(_icosphere(2.0, 3))
    k, h, r = np.nanmean(kh[:, :3], axis=0)
    assert k == pytest.approx(0.25, rel=0.02)
    assert h == pytest.approx(0.5, rel=0.02)
    assert r == pytest.approx(0.5, rel=0.05)


def _naive_curvature(mesh: Mesh, v: int) -> tuple[float, float]:
    """Eq. 3 straight from the definition, edge by edge (independent of the engine)."""
    V, F = mesh.vertices, mesh.faces
    star = [f for f in F.tolist() if v in f]
    area = sum(0.5 * np.linalg.norm(np.cross(V[b] - V[a], V[c] - V[a])) for a, b, c in star)
    alpha = 0.0
    for f in star:
        o = [w for w in f if w != v]
        e1, e2 = V[o[0]] - V[v], V[o[1]] - V[v]
        alpha += math.acos(np.dot(e1, e2) / np.linalg.norm(e1) / np.linalg.norm(e2))
    hsum = 0.0
    for w in {w for f in star for w in f if w != v}:
        two = [f for f in star if w in f]
        n = [np.cross(V[f[1]] - V[f[0]], V[f[2]] - V[f[0]]) for f in two]
        n = [x / np.linalg.norm(x) for x in n]
        beta = math.acos(float(np.clip(np.dot(n[0], n[1]), -1, 1)))
        hsum += np.linalg.norm(V[w] - V[v]) * beta
    return (2 * math.pi - alpha) / (area / 3), 0.25 * hsum / (area / 3)


def test_curvature_matches_naive_reference(ellipsoid):
    kh = vertex_curvatures(ellipsoid)
    rng = np.random.default_rng(0)
    for v in rng.choice(ellipsoid.n_vertices, 40, replace=False):
        k, h = _naive_curvature(ellipsoid, int(v))
        assert kh[v, 0] == pytest.approx(k, rel=1e-9, abs=1e-6)
        assert kh[v, 1] == pytest.approx(h, rel=1e-9, abs=1e-6)
        assert kh[v, 2] == pytest.approx(math.sqrt(max(0.0, 2 * h * h - k)), rel=1e-9, abs=1e-6)


def test_gauss_bonnet_holds_exactly_on_a_marching_cubes_mesh(ellipsoid):
    # sum_v K(v) A(v) / 3 = sum_v (2 pi - sum alpha) = 2 pi chi, chi = 2 for a sphere
    kh = vertex_curvatures(ellipsoid)
    assert np.nansum(kh[:, 0] * kh[:, 3] / 3) == pytest.approx(4 * math.pi, abs=1e-6)


# ---------------------------------------------------------------------------
# Algorithm 2 (curvature)
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("percent", [20.0, 40.0, 60.0])
def test_curvature_reaches_target_and_keeps_topology(ellipsoid, percent):
    target = target_face_count(ellipsoid.n_faces, percent)
    out, info = simplify_curvature(ellipsoid, target_faces=target, return_info=True)
    assert not info["candidates_exhausted"]
    assert target - 1 <= out.n_faces <= target  # two faces per collapse
    assert info["n_faces_reached"] == out.n_faces
    assert info["n_collapses"] == (ellipsoid.n_faces - out.n_faces) // 2
    assert is_watertight(out) and _vertex_manifold(out)
    assert _euler(out) == 2
    assert mesh_volume_mm3(out) > 0


def test_curvature_never_moves_vertices(ellipsoid):
    # [A28]: v_j keeps its position, so V(M2) is a subset of V(M1)
    out = simplify_curvature(ellipsoid, target_faces=ellipsoid.n_faces // 2)
    original = {tuple(p) for p in ellipsoid.vertices.tolist()}
    assert all(tuple(p) in original for p in out.vertices.tolist())


def test_curvature_removes_low_curvedness_vertices_first(ellipsoid):
    # every removed vertex was a candidate: below the threshold tau when it was popped;
    # at the start, removed vertices have lower R than kept ones on average
    out, info = simplify_curvature(ellipsoid, target_faces=int(0.9 * ellipsoid.n_faces),
                                   return_info=True)  # fmt: skip
    r = vertex_curvatures(ellipsoid)[:, 2]
    assert info["tau"] == pytest.approx(np.nanmean(r))
    original = {tuple(p): i for i, p in enumerate(ellipsoid.vertices.tolist())}
    kept = np.zeros(ellipsoid.n_vertices, bool)
    kept[[original[tuple(p)] for p in out.vertices.tolist()]] = True
    assert np.nanmean(r[~kept]) < 0.8 * info["tau"]
    assert info["n_candidates_initial"] == int(np.count_nonzero(r < info["tau"]))


def test_curvature_stops_when_candidates_run_out_and_reports_it(ellipsoid):
    out, info = simplify_mesh(ellipsoid, method="curvature", reduction_percent=99.0,
                              return_info=True)  # fmt: skip
    assert info["candidates_exhausted"] is True
    assert out.n_faces == info["n_faces_reached"] > info["target_faces"]
    assert info["reduction_reached_percent"] == pytest.approx(
        100 * (1 - out.n_faces / ellipsoid.n_faces)
    )
    assert is_watertight(out)


def test_no_root_reading_changes_the_candidate_set(ellipsoid):
    target = ellipsoid.n_faces // 2
    _, a = simplify_curvature(ellipsoid, target_faces=target, return_info=True)
    _, b = simplify_curvature(ellipsoid, target_faces=target, curvedness="no_root",
                              return_info=True)  # fmt: skip
    r = vertex_curvatures(ellipsoid)[:, 2]
    assert b["tau"] == pytest.approx(np.nanmean(r**2))
    assert a["n_candidates_initial"] != b["n_candidates_initial"]


def test_flat_faces_collapse_without_volume_change():
    # a box: its marching-cubes faces and bevels are planar, so every candidate
    # collapse has V(t) = 0 and the enclosed volume stays exact
    mask = np.zeros((14, 16, 18), bool)
    mask[2:12, 2:14, 2:16] = True
    mesh = extract_surface(mask, np.diag([1.0, 1.0, 1.0, 1.0]))
    out = simplify_mesh(mesh, method="curvature", reduction_percent=40.0)
    assert out.n_faces < mesh.n_faces
    assert mesh_volume_mm3(out) == pytest.approx(mesh_volume_mm3(mesh), rel=1e-12)


def test_curvature_is_deterministic(ellipsoid):
    a = simplify_curvature(ellipsoid, target_faces=1000)
    b = simplify_curvature(ellipsoid, target_faces=1000)
    np.testing.assert_array_equal(a.faces, b.faces)
    np.testing.assert_array_equal(a.vertices, b.vertices)


# ---------------------------------------------------------------------------
# memoryless (Lindstrom-Turk)
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("percent", [40.0, 80.0, 90.0])
def test_memoryless_preserves_volume_exactly(ellipsoid, percent):
    target = target_face_count(ellipsoid.n_faces, percent)
    out, info = simplify_memoryless(ellipsoid, target_faces=target, return_info=True)
    assert target - 1 <= out.n_faces <= target
    assert is_watertight(out) and _vertex_manifold(out) and _euler(out) == 2
    # every collapse satisfies sum_t V_t(p) = 0: the enclosed volume is unchanged
    assert mesh_volume_mm3(out) == pytest.approx(mesh_volume_mm3(ellipsoid), rel=1e-9)
    # and stays within the marching-cubes discretisation error of the analytic ellipsoid
    analytic = 4 / 3 * math.pi * (9.0 * 1.2) * (12.0 * 0.9) * (10.0 * 1.0)
    assert mesh_volume_mm3(out) == pytest.approx(analytic, rel=0.03)


def test_memoryless_vertices_stay_near_the_surface():
    sphere = _icosphere(10.0, 4)
    out = simplify_memoryless(sphere, target_faces=sphere.n_faces // 5)
    dist = np.linalg.norm(out.vertices, axis=1)
    assert np.all(np.abs(dist - 10.0) < 0.5)  # optimal placement, not the chord


# ---------------------------------------------------------------------------
# topology: property test over random blobs
# ---------------------------------------------------------------------------


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    seed=st.integers(0, 10_000),
    method=st.sampled_from(["curvature", "memoryless"]),
    percent=st.sampled_from([20.0, 50.0, 70.0, 90.0]),
)
def test_random_blobs_stay_closed_manifolds(seed, method, percent):
    mesh = _blob_mesh(seed)
    chi = _euler(mesh)
    out, info = simplify_mesh(mesh, method=method, reduction_percent=percent, return_info=True)
    assert info["watertight"] is True
    assert is_watertight(out)
    assert _vertex_manifold(out)
    assert edge_manifold_report(out)["n_duplicate_faces"] == 0
    assert _euler(out) == chi  # collapses never change the topology
    assert mesh_volume_mm3(out) > 0
    if not info["candidates_exhausted"]:
        assert out.n_faces <= info["target_faces"]


# ---------------------------------------------------------------------------
# bad input
# ---------------------------------------------------------------------------


def test_open_mesh_is_refused_with_counts(ellipsoid):
    open_mesh = Mesh(ellipsoid.vertices, ellipsoid.faces[1:])
    for method in ("curvature", "memoryless"):
        with pytest.raises(InputError, match=r"closed.*3 boundary"):
            simplify_mesh(open_mesh, method=method, reduction_percent=50.0)


def test_non_manifold_edge_is_refused():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1], [1, 1, 1]], float)
    f = np.array([[0, 1, 2], [0, 1, 3], [0, 1, 4], [0, 1, 5]])
    with pytest.raises(InputError, match="non-manifold"):
        simplify_curvature(Mesh(v, f), target_faces=2)


def test_pinched_vertex_is_kept_and_the_rest_simplified():
    # two balls touching at one voxel corner: a vertex-pinch in the welded mesh
    # would be locked; build a pinch explicitly from two icospheres sharing a vertex
    a = _icosphere(5.0, 2)
    b = Mesh(a.vertices * [1, 1, -1] + [0, 0, 2 * a.vertices[:, 2].max()], a.faces[:, ::-1])
    top = int(np.argmax(a.vertices[:, 2]))
    bottom_b = int(np.argmin(b.vertices[:, 2]))
    shift = a.n_vertices
    fb = b.faces + shift
    fb[fb == bottom_b + shift] = top
    both = Mesh(np.vstack([a.vertices, b.vertices]), np.vstack([a.faces, fb]))
    both = Mesh(*_drop_unused(both))
    out, info = simplify_curvature(both, target_faces=both.n_faces // 2, return_info=True)
    assert info["n_pinched_vertices"] == 1
    assert is_watertight(out)
    assert any(np.allclose(p, a.vertices[top]) for p in out.vertices)


def _drop_unused(mesh):
    used = np.unique(mesh.faces)
    remap = np.full(mesh.n_vertices, -1)
    remap[used] = np.arange(len(used))
    return mesh.vertices[used], remap[mesh.faces]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"target_faces": 2.0}, "must be an integer"),
        ({"target_faces": 0}, r"\[1, "),
        ({"target_faces": 10**9}, r"\[1, "),
        ({"target_faces": 10, "curvedness": "cube"}, "curvedness"),
    ],
)
def test_simplify_curvature_validation(ellipsoid, kwargs, match):
    with pytest.raises(InputError, match=match):
        simplify_curvature(ellipsoid, **kwargs)


def test_simplify_memoryless_rejects_non_mesh():
    with pytest.raises(InputError, match="tumor3d.geometry.mesh.Mesh"):
        simplify_memoryless("mesh", target_faces=4)
