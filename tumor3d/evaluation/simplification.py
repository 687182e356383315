r"""Evaluation of mesh simplification (spec section 9, Eq. 11, [A28]).

Pure functions on :class:`~tumor3d.geometry.mesh.Mesh` objects that return numbers or
table rows (lists of flat dicts); the evaluation registry calls
:func:`simplification_rows`.

* :func:`vertex_hausdorff` -- the paper's Eq. 11,
  ``SHD(M1, M2) = max(max_{v in M1} d_v(M2), max_{v in M2} d_v(M1))`` with
  ``d_v`` the distance to the nearest *vertex* (KD-tree). A method that never
  moves vertices (the paper's) has ``V(M2) subset V(M1)``, so its second term
  is 0 and Eq. 11 favours it ([A28]);
* :func:`surface_distances` -- therefore also the point-to-*surface*
  symmetric Hausdorff and mean distances of Cignoni et al. (Metro): area-
  uniform samples (plus all vertices) of each mesh, exact distance to the
  other mesh's triangles (Open3D ``RaycastingScene``);
* :func:`volume_change_percent`, :func:`triangle_quality` (Eq. 5 ``S(t)``
  and the minimum angle) and the watertightness of the result.

References
----------
P. Cignoni, C. Rocchini, R. Scopigno, "Metro: measuring error on simplified
surfaces", Computer Graphics Forum 17(2), 1998, doi:10.1111/1467-8659.00236.
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterable
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from tumor3d.errors import InputError
from tumor3d.geometry.mesh import Mesh
from tumor3d.geometry.surface import edge_manifold_report, is_watertight, mesh_volume_mm3

__all__ = [
    "sample_surface",
    "simplification_rows",
    "surface_distances",
    "triangle_quality",
    "vertex_hausdorff",
    "volume_change_percent",
]


def _check_mesh(mesh: Any, name: str) -> Mesh:
    if not isinstance(mesh, Mesh):
        raise InputError(f"{name} must be a tumor3d.geometry.mesh.Mesh, got {type(mesh).__name__}")
    if mesh.is_empty:
        raise InputError(f"{name} is empty (no faces)")
    return mesh


def vertex_hausdorff(mesh_a: Mesh, mesh_b: Mesh) -> dict[str, float]:
    """Eq. 11: symmetric Hausdorff distance between the vertex sets (mm).

    Parameters
    ----------
    mesh_a, mesh_b : Mesh
        Typically the original and the simplified mesh (RAS mm).

    Returns
    -------
    dict
        ``shd_vertex_mm`` (Eq. 11), ``d_ab_mm`` = ``max_{v in A} d_v(B)`` and
        ``d_ba_mm`` = ``max_{v in B} d_v(A)``.
    """
    a = _check_mesh(mesh_a, "mesh_a").vertices
    b = _check_mesh(mesh_b, "mesh_b").vertices
    d_ab = float(cKDTree(b).query(a, k=1)[0].max())
    d_ba = float(cKDTree(a).query(b, k=1)[0].max())
    return {"shd_vertex_mm": max(d_ab, d_ba), "d_ab_mm": d_ab, "d_ba_mm": d_ba}


def sample_surface(mesh: Mesh, n_samples: int, *, seed: int = 0) -> np.ndarray:
    """Area-uniform random points on a mesh's triangles.

    A point ``a + s (b - a) + t (c - a)`` with ``(s, t)`` uniform on the unit
    triangle (reflected square), in a face drawn with probability
    proportional to its area.

    Returns
    -------
    (n_samples, 3) float64 ndarray
        Points in the mesh's coordinates (mm).
    """
    _check_mesh(mesh, "mesh")
    if isinstance(n_samples, bool) or not isinstance(n_samples, (int, np.integer)):
        raise InputError(f"n_samples must be an integer, got {n_samples!r}")
    if n_samples < 0:
        raise InputError(f"n_samples must be >= 0, got {n_samples}")
    v, f = mesh.vertices, mesh.faces
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    rng = np.random.default_rng(seed)
    if area.sum() <= 0:
        return a[rng.integers(0, len(f), n_samples)]
    face = rng.choice(len(f), size=n_samples, p=area / area.sum())
    s, t = rng.random((2, n_samples))
    flip = s + t > 1
    s[flip], t[flip] = 1 - s[flip], 1 - t[flip]
    return a[face] + s[:, None] * (b[face] - a[face]) + t[:, None] * (c[face] - a[face])


def _distance_to_surface(points: np.ndarray, mesh: Mesh) -> np.ndarray:
    import open3d as o3d  # deferred: a large extension, only needed here

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.ascontiguousarray(mesh.vertices, dtype=np.float32)),
        o3d.core.Tensor(np.ascontiguousarray(mesh.faces, dtype=np.uint32)),
    )
    query = o3d.core.Tensor(np.ascontiguousarray(points, dtype=np.float32))
    return scene.compute_distance(query).numpy().astype(np.float64)


def surface_distances(
    mesh_a: Mesh, mesh_b: Mesh, *, n_samples: int = 20000, seed: int = 0
) -> dict[str, float]:
    """Point-to-surface symmetric Hausdorff and mean distance (Metro, [A28]).

    Each mesh is sampled with ``n_samples`` area-uniform points plus all its
    vertices; each sample's exact distance to the other mesh's triangles is
    computed. ``H(A, B) = max(max_{p in A} d(p, B), max_{q in B} d(q, A))``
    and the mean distance is the average of the two one-sided means.

    Parameters
    ----------
    mesh_a, mesh_b : Mesh
    n_samples : int, optional
        Random surface samples per mesh (besides the vertices).
    seed : int, optional
        Seed of the sampler (results are deterministic).

    Returns
    -------
    dict
        ``hausdorff_mm``, ``mean_distance_mm``, ``d_ab_max_mm``,
        ``d_ba_max_mm``, ``d_ab_mean_mm``, ``d_ba_mean_mm``. Distances are
        computed in float32 (Open3D): about 1e-5 mm resolution at 100 mm.
    """
    _check_mesh(mesh_a, "mesh_a")
    _check_mesh(mesh_b, "mesh_b")
    pa = np.vstack([mesh_a.vertices, sample_surface(mesh_a, n_samples, seed=seed)])
    pb = np.vstack([mesh_b.vertices, sample_surface(mesh_b, n_samples, seed=seed + 1)])
    d_ab = _distance_to_surface(pa, mesh_b)
    d_ba = _distance_to_surface(pb, mesh_a)
    return {
        "hausdorff_mm": float(max(d_ab.max(), d_ba.max())),
        "mean_distance_mm": float(0.5 * (d_ab.mean() + d_ba.mean())),
        "d_ab_max_mm": float(d_ab.max()),
        "d_ba_max_mm": float(d_ba.max()),
        "d_ab_mean_mm": float(d_ab.mean()),
        "d_ba_mean_mm": float(d_ba.mean()),
    }


def volume_change_percent(original: Mesh, simplified: Mesh) -> float:
    """``100 (V(simplified) / V(original) - 1)`` of the enclosed volumes."""
    v0 = mesh_volume_mm3(_check_mesh(original, "original"))
    if v0 == 0:
        raise InputError("original encloses no volume")
    return 100.0 * (mesh_volume_mm3(_check_mesh(simplified, "simplified")) / v0 - 1.0)


def triangle_quality(mesh: Mesh) -> dict[str, float]:
    r"""Triangle-shape statistics: Eq. 5 quality and the minimum angle.

    .. math:: S(t) = \frac{4 \sqrt{3} A_t}{l_1^2 + l_2^2 + l_3^2}

    (1 for an equilateral triangle, 0 for a degenerate one).

    Returns
    -------
    dict
        ``quality_mean``, ``quality_min``, ``quality_p05`` (5th percentile),
        ``fraction_quality_below_0_3``, ``min_angle_deg`` (smallest angle
        of any face), ``min_angle_mean_deg`` (mean over faces of each face's
        smallest angle).
    """
    _check_mesh(mesh, "mesh")
    v, f = mesh.vertices, mesh.faces
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    la = np.linalg.norm(b - c, axis=1)
    lb = np.linalg.norm(c - a, axis=1)
    lc = np.linalg.norm(a - b, axis=1)
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    l2 = la**2 + lb**2 + lc**2
    q = np.where(l2 > 0, 4.0 * math.sqrt(3.0) * area / np.where(l2 > 0, l2, 1.0), 0.0)
    # the smallest angle faces the shortest side: sin(alpha) = 2 A / (b c)
    sides = np.sort(np.column_stack([la, lb, lc]), axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_min = (sides[:, 1] ** 2 + sides[:, 2] ** 2 - sides[:, 0] ** 2) / (
            2 * sides[:, 1] * sides[:, 2]
        )
    min_angle = np.degrees(np.arccos(np.clip(np.nan_to_num(cos_min, nan=1.0), -1, 1)))
    return {
        "quality_mean": float(q.mean()),
        "quality_min": float(q.min()),
        "quality_p05": float(np.percentile(q, 5)),
        "fraction_quality_below_0_3": float(np.mean(q < 0.3)),
        "min_angle_deg": float(min_angle.min()),
        "min_angle_mean_deg": float(min_angle.mean()),
    }


def simplification_rows(
    mesh: Mesh,
    *,
    case: str,
    methods: Iterable[str] = ("curvature", "memoryless", "qem"),
    reduction_percents: Iterable[float] = (20.0, 40.0, 60.0, 80.0, 90.0),
    n_samples: int = 20000,
    seed: int = 0,
) -> list[dict[str, Any]]:
    """Simplify ``mesh`` by every method at every ``P`` and measure each result.

    Parameters
    ----------
    mesh : Mesh
        The marching-cubes surface of one case (closed, outward).
    case : str
        Name of the case, copied into every row.
    methods : iterable of str, optional
        Methods of :func:`tumor3d.simplify.simplify_mesh`.
    reduction_percents : iterable of float, optional
        ``P`` values in (0, 100).
    n_samples, seed : int, optional
        Passed to :func:`surface_distances`.

    Returns
    -------
    list of dict
        One row per (method, P): ``case``, ``method``, ``reduction_percent``,
        ``faces_in``, ``faces_target``, ``faces_out``,
        ``reduction_reached_percent``, ``candidates_exhausted``,
        ``time_s`` (wall clock of the simplification), ``watertight``,
        ``n_nonmanifold_edges``, ``n_boundary_edges``,
        ``volume_change_percent``, the Eq. 11 terms
        (:func:`vertex_hausdorff`), the surface distances
        (:func:`surface_distances`) and the quality statistics
        (:func:`triangle_quality`).
    """
    from tumor3d.simplify import simplify_mesh  # the evaluation depends on the simplifier

    _check_mesh(mesh, "mesh")
    if not isinstance(case, str):
        raise InputError(f"case must be a string, got {case!r}")
    rows: list[dict[str, Any]] = []
    for method in methods:
        for p in reduction_percents:
            t0 = time.perf_counter()
            out, info = simplify_mesh(
                mesh, method=method, reduction_percent=float(p), return_info=True
            )
            elapsed = time.perf_counter() - t0
            topo = edge_manifold_report(out)
            row: dict[str, Any] = {
                "case": case,
                "method": method,
                "reduction_percent": float(p),
                "faces_in": mesh.n_faces,
                "faces_target": info["target_faces"],
                "faces_out": out.n_faces,
                "reduction_reached_percent": info["reduction_reached_percent"],
                "candidates_exhausted": bool(info.get("candidates_exhausted", False)),
                "time_s": elapsed,
                "watertight": bool(is_watertight(out)),
                "n_nonmanifold_edges": topo["n_nonmanifold_edges"],
                "n_boundary_edges": topo["n_boundary_edges"],
                "volume_change_percent": volume_change_percent(mesh, out),
            }
            row.update(vertex_hausdorff(mesh, out))
            row.update(surface_distances(mesh, out, n_samples=n_samples, seed=seed))
            row.update(triangle_quality(out))
            rows.append(row)
    return rows
