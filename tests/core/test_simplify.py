"""Tests of tumor3d.simplify: face budget of Algorithm 2, the method registry and QEM."""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.geometry.mesh import Mesh
from tumor3d.geometry.surface import extract_surface, is_watertight, mesh_volume_mm3
from tumor3d.simplify import METHODS, simplify_mesh, target_face_count
from tumor3d.simplify.curvature import vertex_curvatures
from tumor3d.simplify.qem import simplify_qem

SPACING_ZYX = (1.0, 0.9, 0.9)
RADIUS_MM = 12.0


def _sphere_mesh(radius_mm=RADIUS_MM, spacing_zyx=SPACING_ZYX):
    n = [int(2 * radius_mm / s) + 6 for s in spacing_zyx]
    centre = [(k - 1) / 2 for k in n]
    z, y, x = np.ogrid[: n[0], : n[1], : n[2]]
    r2 = sum(((a - c) * s) ** 2 for a, c, s in zip((z, y, x), centre, spacing_zyx, strict=True))
    dz, dy, dx = spacing_zyx
    affine = np.diag([dx, dy, dz, 1.0])
    centre_ras = (affine @ [centre[2], centre[1], centre[0], 1.0])[:3]
    return extract_surface(r2 <= radius_mm**2, affine), centre_ras


@pytest.fixture(scope="module")
def sphere():
    return _sphere_mesh()


# ---------------------------------------------------------------------------
# target_face_count
# ---------------------------------------------------------------------------


def test_target_face_count_reproduces_fig9():
    assert [target_face_count(6116, p) for p in (0, 40, 60, 80)] == [6116, 3669, 2446, 1223]


def test_target_face_count_is_exact_where_floats_round_down():
    # 10 * (1 - 80 / 100) == 1.9999999999999996 in floating point
    assert math.floor(10 * (1 - 80.0 / 100)) == 1
    assert target_face_count(10, 80.0) == 2
    assert target_face_count(20, 90.0) == 2
    assert target_face_count(10, 33.3) == 6  # floor(6.67)
    assert target_face_count(0, 50.0) == 0


@pytest.mark.parametrize(
    ("n", "p", "match"),
    [
        (-1, 10.0, "n_faces"),
        (1.5, 10.0, "n_faces"),
        (10, -0.1, r"\[0, 100\)"),
        (10, 100.0, r"\[0, 100\)"),
        (10, float("nan"), r"\[0, 100\)"),
        (10, "40", "must be a number"),
        (10, True, "must be a number"),
    ],
)
def test_target_face_count_validation(n, p, match):
    with pytest.raises(InputError, match=match):
        target_face_count(n, p)


# ---------------------------------------------------------------------------
# QEM through simplify_mesh
# ---------------------------------------------------------------------------


@pytest.mark.parametrize("percent", [40.0, 60.0, 80.0])
def test_qem_reaches_target_keeps_watertight_and_volume(sphere, percent):
    mesh, centre = sphere
    out, info = simplify_mesh(mesh, method="qem", reduction_percent=percent, return_info=True)
    target = target_face_count(mesh.n_faces, percent)
    # Each collapse on a closed mesh removes two faces and the algorithm stops
    # at the first count <= target: measured exactly target or target - 1.
    assert target - 2 <= out.n_faces <= target
    assert info["target_faces"] == target
    assert info["n_faces_in"] == mesh.n_faces
    assert info["n_faces_out"] == out.n_faces
    assert info["faces_over_target"] == out.n_faces - target
    assert info["watertight"] is True
    assert is_watertight(out)
    vol0 = mesh_volume_mm3(mesh)
    # measured: |dV| < 1e-4 relative up to P = 80 on this sphere
    assert abs(mesh_volume_mm3(out) / vol0 - 1) < 0.01
    # vertices stay near the sphere (QEM moves them to quadric optima)
    dist = np.linalg.norm(out.vertices - centre, axis=1)
    assert np.all(np.abs(dist - RADIUS_MM) < 1.5)


@pytest.mark.parametrize("method", METHODS)
def test_orientation_is_outward_even_for_inward_input(sphere, method):
    mesh, _ = sphere
    inward = Mesh(mesh.vertices, mesh.faces[:, ::-1])
    out = simplify_mesh(inward, method=method, reduction_percent=60.0)
    assert mesh_volume_mm3(out) > 0
    assert is_watertight(out)


@pytest.mark.parametrize("method", METHODS)
def test_zero_percent_is_identity(sphere, method):
    mesh, _ = sphere
    out, info = simplify_mesh(mesh, method=method, reduction_percent=0.0, return_info=True)
    assert out is mesh
    assert info["n_faces_out"] == info["target_faces"] == mesh.n_faces
    assert info["simplified"] is False


@pytest.mark.parametrize("method", METHODS)
def test_input_mesh_not_modified(sphere, method):
    mesh, _ = sphere
    v, f = mesh.vertices.copy(), mesh.faces.copy()
    simplify_mesh(mesh, method=method, reduction_percent=70.0)
    np.testing.assert_array_equal(mesh.vertices, v)
    np.testing.assert_array_equal(mesh.faces, f)


@pytest.mark.parametrize("method", METHODS)
def test_info_is_consistent(sphere, method):
    mesh, _ = sphere
    out, info = simplify_mesh(mesh, method=method, reduction_percent=50.0, return_info=True)
    assert info["method"] == method
    assert info["simplified"] is True and info["reason"] is None
    assert info["n_faces_out"] == out.n_faces
    assert info["reduction_reached_percent"] == pytest.approx(
        100 * (1 - out.n_faces / mesh.n_faces)
    )
    assert info["watertight"] == is_watertight(out)


def test_qem_is_deterministic_and_thread_safe(sphere):
    mesh, _ = sphere
    ref = simplify_mesh(mesh, method="qem", reduction_percent=50.0)
    with ThreadPoolExecutor(max_workers=4) as pool:
        outs = list(
            pool.map(
                lambda _: simplify_mesh(mesh, method="qem", reduction_percent=50.0), range(8)
            )
        )
    for out in outs:
        np.testing.assert_array_equal(out.faces, ref.faces)
        np.testing.assert_array_equal(out.vertices, ref.vertices)


def test_options_are_forwarded_to_the_method(sphere, monkeypatch):
    # fast_simplification's result does not change with agg on this sphere, so a
    # spy in the registry checks what simplify_mesh passes on
    import tumor3d.simplify as simplify_pkg

    mesh, _ = sphere
    seen = {}

    def spy(m, **kwargs):
        seen.update(kwargs)
        return simplify_qem(m, **kwargs)

    allowed = simplify_pkg._METHODS["qem"][1]
    monkeypatch.setitem(simplify_pkg._METHODS, "qem", (spy, allowed))
    simplify_mesh(mesh, method="qem", reduction_percent=60.0, aggressiveness=3.0)
    assert seen["aggressiveness"] == 3.0
    assert seen["target_faces"] == target_face_count(mesh.n_faces, 60.0)


def test_curvedness_is_forwarded(sphere):
    mesh, _ = sphere
    _, sqrt = simplify_mesh(mesh, method="curvature", reduction_percent=40.0, return_info=True)
    _, no_root = simplify_mesh(mesh, method="curvature", reduction_percent=40.0,
                               curvedness="no_root", return_info=True)  # fmt: skip
    r = vertex_curvatures(mesh)[:, 2]
    assert sqrt["tau"] == pytest.approx(np.nanmean(r))
    assert no_root["tau"] == pytest.approx(np.nanmean(r**2))


def test_methods_registry():
    assert set(METHODS) == {"curvature", "memoryless", "qem"}


_TETRA_FOR_PASS = Mesh(
    np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float),
    np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]),
)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("percent", [50.0, 99.0])
def test_tiny_mesh_passes_through_unchanged(method, percent):
    out, info = simplify_mesh(
        _TETRA_FOR_PASS, method=method, reduction_percent=percent, return_info=True
    )
    assert out is _TETRA_FOR_PASS
    assert info["simplified"] is False
    assert "below 4" in info["reason"]
    assert info["watertight"] is True


def test_empty_mesh_passes_through():
    empty = Mesh(np.zeros((0, 3)), np.zeros((0, 3), int))
    out, info = simplify_mesh(empty, reduction_percent=60.0, return_info=True)
    assert out is empty
    assert info["simplified"] is False and "empty" in info["reason"]
    assert info["watertight"] is False


# ---------------------------------------------------------------------------
# validation
# ---------------------------------------------------------------------------

_TETRA = Mesh(
    np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float),
    np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]]),
)


@pytest.mark.parametrize(
    ("mesh", "kwargs", "match"),
    [
        ("mesh", {"reduction_percent": 50.0}, "tumor3d.geometry.mesh.Mesh"),
        (_TETRA, {"reduction_percent": 50.0, "method": "magic"}, "unknown simplification method"),
        (_TETRA, {"reduction_percent": 50.0, "agg": 3.0}, r"unknown option\(s\) \['agg'\]"),
        (_TETRA, {"reduction_percent": -5.0}, r"\[0, 100\)"),
        (_TETRA, {"reduction_percent": 100.0}, r"\[0, 100\)"),
        (_TETRA, {"reduction_percent": 50.0, "method": "qem", "curvedness": "x"}, "curvedness"),
    ],
)
def test_simplify_mesh_validation(mesh, kwargs, match):
    with pytest.raises(InputError, match=match):
        simplify_mesh(mesh, **kwargs)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"target_faces": 2.0}, "must be an integer"),
        ({"target_faces": 0}, r"\[1, 4\]"),
        ({"target_faces": 5}, r"\[1, 4\]"),
        ({"target_faces": 4, "aggressiveness": 11.0}, "aggressiveness"),
    ],
)
def test_simplify_qem_validation(kwargs, match):
    with pytest.raises(InputError, match=match):
        simplify_qem(_TETRA, **kwargs)


def test_simplify_qem_rejects_non_mesh():
    with pytest.raises(InputError, match="tumor3d.geometry.mesh.Mesh"):
        simplify_qem([1, 2, 3], target_faces=1)


# ---------------------------------------------------------------------------
# curvature: why it stops above the target, and tau="refresh"
# ---------------------------------------------------------------------------


def test_curvature_says_why_it_stops_above_the_target_and_refresh_reaches_it(sphere):
    # Algorithm 2 stops when its candidates (R < tau, tau fixed before the loop,
    # [A22]) run out: at P = 90 % on this sphere that is above F_target
    mesh, _ = sphere
    target = target_face_count(mesh.n_faces, 90.0)
    out, info = simplify_mesh(mesh, method="curvature", reduction_percent=90.0, return_info=True)
    assert info["candidates_exhausted"] and out.n_faces > target
    assert info["tau_passes"] == 1
    assert "candidate set ran out" in info["stop_reason"]
    assert f"{out.n_faces} faces" in info["stop_reason"]
    # refreshing tau whenever the candidates run out reaches the target
    ref, rinfo = simplify_mesh(
        mesh, method="curvature", reduction_percent=90.0, tau="refresh", return_info=True
    )
    assert target - 1 <= ref.n_faces <= target  # a collapse removes two faces
    assert rinfo["stop_reason"] is None and not rinfo["candidates_exhausted"]
    assert rinfo["tau_passes"] >= 2 and rinfo["n_collapses"] > info["n_collapses"]
    assert is_watertight(ref)
    # the kept vertices are input vertices (half-edge collapse, v_j does not move)
    kept = {tuple(v) for v in np.round(mesh.vertices, 9)}
    assert all(tuple(v) in kept for v in np.round(ref.vertices, 9))
    # the first pass is the paper's: its tau is the one reported
    assert rinfo["tau"] == pytest.approx(info["tau"])


def test_curvature_reaching_the_target_has_no_stop_reason(sphere):
    mesh, _ = sphere
    out, info = simplify_mesh(mesh, method="curvature", reduction_percent=40.0, return_info=True)
    assert out.n_faces <= target_face_count(mesh.n_faces, 40.0)
    assert info["stop_reason"] is None and info["tau_passes"] == 1


def test_curvature_tau_option_is_validated(sphere):
    mesh, _ = sphere
    with pytest.raises(InputError, match="tau must be one of"):
        simplify_mesh(mesh, method="curvature", reduction_percent=40.0, tau="often")
    with pytest.raises(InputError, match="unknown option"):
        simplify_mesh(mesh, method="memoryless", reduction_percent=40.0, tau="refresh")


def test_curvature_ring_update_lazy_and_eager(sphere):
    # step 6 lazy (default) or eager (the paper's order): both reach the target with
    # a closed mesh of input vertices; the order of collapses, and so the mesh, differ
    mesh, _ = sphere
    target = target_face_count(mesh.n_faces, 60.0)
    outs = {}
    for ring_update in ("lazy", "eager"):
        out, info = simplify_mesh(
            mesh, method="curvature", reduction_percent=60.0, ring_update=ring_update,
            return_info=True,
        )  # fmt: skip
        assert target - 1 <= out.n_faces <= target and info["stop_reason"] is None
        assert is_watertight(out)
        kept = {tuple(v) for v in np.round(mesh.vertices, 9)}
        assert all(tuple(v) in kept for v in np.round(out.vertices, 9))
        outs[ring_update] = out
    assert not np.array_equal(outs["lazy"].vertices, outs["eager"].vertices)
    with pytest.raises(InputError, match="ring_update must be one of"):
        simplify_mesh(mesh, method="curvature", reduction_percent=40.0, ring_update="never")
