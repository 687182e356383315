"""Iso-surface extraction from a binary tumour mask, and mesh measurements.

Implements section 5 of the specification (marching cubes, [A15], [A16])
and the mesh checks the later stages rely on:

* :func:`extract_surface` -- zero-pad the mask, run marching cubes
  (Lewiner et al. 2003, ``skimage.measure.marching_cubes(method='lewiner')``)
  in voxel-index space, map the vertices to RAS millimetres through the
  affine, weld, clean and orient the triangles outward;
* :func:`mesh_volume_mm3`, :func:`mesh_area_mm2` -- enclosed volume (divergence
  theorem) and surface area;
* :func:`edge_manifold_report`, :func:`is_watertight` -- vectorised edge
  topology checks (closed, consistently oriented 2-manifold edges).

Why Lewiner's MC33 tables rather than Montani's 21 cases
--------------------------------------------------------
The paper cites Montani et al. [MSS94], who add to the 15 Lorensen-Cline
cases the complements of the six cases with ambiguous faces (3, 6, 7, 10,
12, 13) and resolve every ambiguous face by one fixed rule, so that
neighbouring cubes agree and the surface is crack-free. Lewiner et al.
implement Chernyaev's MC33 instead: each ambiguous face is resolved by the
asymptotic decider and the cube interior by an interior test, so the
triangulation is the topology of the trilinear interpolant, with the same
crack-free guarantee; it ships in scikit-image, tested and fast ([A16]). On
binary masks every face saddle equals the iso-value, so each decider is a
deterministic tie: face counts can differ slightly from a 21-case table,
and diagonal voxels may be joined (a 2x2x2 block can give a torus), but the
surface stays closed. The tests check this on all 255 single-cube and all
4095 two-cube (2x2x3) corner patterns, which contain every ambiguous case
and its complement: watertight, edge- and vertex-manifold, consistently
oriented. (scikit-image's ``'lorensen'`` table, which the spec forbids, was
also watertight on those patterns and on 300 random 7x7x7 masks in
scikit-image 0.26: the choice rests on the guarantee, not on an observed
hole.)

References
----------
C. Montani, R. Scateni, R. Scopigno, "A modified look-up table for implicit
disambiguation of marching cubes", The Visual Computer 10(6), 1994,
doi:10.1007/BF01900830.
W. E. Lorensen, H. E. Cline, "Marching cubes", SIGGRAPH 1987,
doi:10.1145/37402.37422.
T. Lewiner, H. Lopes, A. W. Vieira, G. Tavares, "Efficient implementation of
marching cubes' cases with topological guarantees", J. Graphics Tools 8(2),
2003, doi:10.1080/10867651.2003.10487582.
"""

from __future__ import annotations

import numpy as np
from skimage.measure import marching_cubes

from tumor3d.errors import InputError, NoSurfaceError
from tumor3d.geometry.mesh import Mesh
from tumor3d.imaging.affine import zyx_index_to_ras

__all__ = [
    "clean_mesh",
    "edge_manifold_report",
    "extract_surface",
    "is_watertight",
    "mesh_area_mm2",
    "mesh_volume_mm3",
    "orient_outward",
]


# ---------------------------------------------------------------------------
# validation helpers
# ---------------------------------------------------------------------------


def _check_affine(affine: np.ndarray, name: str = "affine") -> np.ndarray:
    aff = np.asarray(affine)
    if aff.shape != (4, 4):
        raise InputError(f"{name} must be a 4x4 array, got shape {aff.shape}")
    if not np.issubdtype(aff.dtype, np.number) or np.iscomplexobj(aff):
        raise InputError(f"{name} must be real-valued, got dtype {aff.dtype}")
    aff = aff.astype(np.float64)
    if not np.all(np.isfinite(aff)):
        raise InputError(f"{name} must be finite")
    if not np.allclose(aff[3], [0.0, 0.0, 0.0, 1.0]):
        raise InputError(f"{name} must have last row [0, 0, 0, 1], got {aff[3].tolist()}")
    if abs(np.linalg.det(aff[:3, :3])) < 1e-12:
        raise InputError(f"{name} is singular (det of its 3x3 part is 0)")
    return aff


def _check_binary_mask(mask: np.ndarray, name: str = "mask") -> np.ndarray:
    """Return ``mask`` as a bool array after checking it is a 3-D 0/1 array."""
    arr = np.asarray(mask)
    if arr.ndim != 3:
        raise InputError(f"{name} must be a 3-D (z, y, x) array, got shape {arr.shape}")
    if arr.dtype == np.bool_:
        return arr
    if not np.issubdtype(arr.dtype, np.integer):
        raise InputError(f"{name} must be bool or integer 0/1, got dtype {arr.dtype}")
    if arr.size and (arr.min() < 0 or arr.max() > 1):
        raise InputError(f"{name} must hold only 0 and 1, got values in [{arr.min()}, {arr.max()}]")
    return arr.astype(bool)


def _check_mesh(mesh: Mesh) -> Mesh:
    if not isinstance(mesh, Mesh):
        raise InputError(f"mesh must be a tumor3d.geometry.mesh.Mesh, got {type(mesh).__name__}")
    return mesh


# ---------------------------------------------------------------------------
# mesh measurements
# ---------------------------------------------------------------------------


def _signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    if len(faces) == 0:
        return 0.0
    # about the vertices' centroid: the same volume for a closed mesh, and no loss of
    # precision far from the origin (1e7 mm of affine translation made the triple
    # products ~1e21 and the volume of a simplified 14 mL ball 53 mL, measured)
    centre = vertices.mean(axis=0)
    v0 = vertices[faces[:, 0]] - centre
    v1 = vertices[faces[:, 1]] - centre
    v2 = vertices[faces[:, 2]] - centre
    return float(np.einsum("ij,ij->i", v0, np.cross(v1, v2)).sum() / 6.0)


def mesh_volume_mm3(mesh: Mesh) -> float:
    r"""Signed volume enclosed by a triangle mesh (divergence theorem).

    .. math:: V = \frac{1}{6} \sum_{t=(v_0, v_1, v_2)} v_0 \cdot (v_1 \times v_2)

    Positive for a closed mesh whose faces are counter-clockwise seen from
    outside (outward normals); negative when every face is flipped. Only
    meaningful (origin-independent) for a closed mesh; computed about the
    vertices' centroid, so that a mesh far from the origin keeps its precision.

    Parameters
    ----------
    mesh : Mesh
        Vertices in RAS mm.

    Returns
    -------
    float
        Signed volume in mm^3 (0 for an empty mesh).
    """
    _check_mesh(mesh)
    return _signed_volume(mesh.vertices, mesh.faces)


def mesh_area_mm2(mesh: Mesh) -> float:
    r"""Total surface area of a triangle mesh.

    .. math:: A = \sum_t \tfrac{1}{2} \lVert (v_1 - v_0) \times (v_2 - v_0) \rVert

    Parameters
    ----------
    mesh : Mesh
        Vertices in RAS mm.

    Returns
    -------
    float
        Area in mm^2 (0 for an empty mesh).
    """
    _check_mesh(mesh)
    if mesh.is_empty:
        return 0.0
    v, f = mesh.vertices, mesh.faces
    cross = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    return float(0.5 * np.linalg.norm(cross, axis=1).sum())


def edge_manifold_report(mesh: Mesh) -> dict[str, int]:
    """Count the edge-topology defects of a triangle mesh.

    Each face ``(a, b, c)`` contributes the directed edges ``a->b``,
    ``b->c`` and ``c->a``. An undirected edge of a closed, consistently
    oriented 2-manifold is used by exactly two faces, once in each direction.
    Fully vectorised (``np.unique`` on one integer key per undirected edge).

    Parameters
    ----------
    mesh : Mesh

    Returns
    -------
    dict of str to int
        ``n_faces``, ``n_edges`` (distinct undirected edges),
        ``n_boundary_edges`` (used by one face), ``n_nonmanifold_edges``
        (used by three or more faces), ``n_inconsistent_edges`` (used by
        two faces in the same direction), ``n_degenerate_faces`` (a vertex
        index repeated within a face; their edges are left out of the edge
        counts) and ``n_duplicate_faces`` (faces beyond the first on the same
        vertex set).
    """
    _check_mesh(mesh)
    f = mesh.faces
    report = {
        "n_faces": int(len(f)),
        "n_edges": 0,
        "n_boundary_edges": 0,
        "n_nonmanifold_edges": 0,
        "n_inconsistent_edges": 0,
        "n_degenerate_faces": 0,
        "n_duplicate_faces": 0,
    }
    if len(f) == 0:
        return report
    degenerate = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])
    report["n_degenerate_faces"] = int(degenerate.sum())
    report["n_duplicate_faces"] = int(len(f) - len(_unique_rows(np.sort(f, axis=1))[0]))
    f = f[~degenerate]  # their edges are not counted
    if len(f) == 0:
        return report

    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=0)
    forward = directed[:, 0] < directed[:, 1]
    keys = np.sort(directed, axis=1)
    n_keys = int(f.max()) + 1  # one int64 key per undirected edge: lo * n + hi
    _, inverse, counts = np.unique(
        keys[:, 0] * n_keys + keys[:, 1], return_inverse=True, return_counts=True
    )
    inverse = inverse.reshape(-1)
    n_forward = np.bincount(inverse, weights=forward, minlength=len(counts))
    report["n_edges"] = int(len(counts))
    report["n_boundary_edges"] = int(np.count_nonzero(counts == 1))
    report["n_nonmanifold_edges"] = int(np.count_nonzero(counts > 2))
    report["n_inconsistent_edges"] = int(np.count_nonzero((counts == 2) & (n_forward != 1)))
    return report


def is_watertight(mesh: Mesh) -> bool:
    """Whether a mesh is closed with consistently oriented manifold edges.

    True iff the mesh has at least one face, no degenerate face, and every
    undirected edge is used by exactly two faces in opposite directions
    (see :func:`edge_manifold_report`).

    Parameters
    ----------
    mesh : Mesh

    Returns
    -------
    bool
    """
    r = edge_manifold_report(mesh)
    return (
        r["n_faces"] > 0
        and r["n_boundary_edges"] == 0
        and r["n_nonmanifold_edges"] == 0
        and r["n_inconsistent_edges"] == 0
        and r["n_degenerate_faces"] == 0
    )


# ---------------------------------------------------------------------------
# cleaning
# ---------------------------------------------------------------------------


def _face_parity(faces: np.ndarray) -> np.ndarray:
    """Flag faces whose cyclic order ascends once rotated to start at their minimum."""
    rot = np.argmin(faces, axis=1)
    rows = np.arange(len(faces))
    second = faces[rows, (rot + 1) % 3]
    third = faces[rows, (rot + 2) % 3]
    return second < third


def _unique_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(a, axis=0, return_inverse=True)`` for an (n, 3) array, by one lexsort.

    Same lexicographic order as :func:`numpy.unique`, several times faster
    on large arrays (no structured-dtype view).
    """
    n = len(a)
    order = np.lexsort((a[:, 2], a[:, 1], a[:, 0]))
    s = a[order]
    new = np.ones(n, dtype=bool)
    if n > 1:
        new[1:] = np.any(s[1:] != s[:-1], axis=1)
    inverse = np.empty(n, dtype=np.int64)
    inverse[order] = np.cumsum(new) - 1
    return s[new], inverse


def _clean(
    vertices: np.ndarray, faces: np.ndarray, *, weld: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Weld identical vertices, drop degenerate/duplicate faces and unused vertices.

    Welding (optional) is exact: bitwise-equal coordinates become one
    vertex. Faces sharing one vertex set are resolved by their orientations:
    oppositely oriented copies cancel in pairs (a zero-volume double sheet,
    which skimage's Lewiner tables emit on some ambiguous binary
    configurations and which would otherwise leave non-manifold edges); of
    the copies left, the first in input order is kept.
    """
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    vertices = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    if len(faces) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    if weld:
        uniq, inverse = _unique_rows(vertices)
        f = inverse[faces]
    else:
        uniq, f = vertices, faces
    keep = (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
    f = f[keep]
    if len(f) == 0:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    _, group = _unique_rows(np.sort(f, axis=1))
    sign = np.where(_face_parity(f), 1, -1)
    net = np.bincount(group, weights=sign).astype(np.int64)
    # keep one face per vertex set whose orientations do not cancel, with the
    # majority orientation: the first face of that orientation in input order
    want = np.sign(net)[group]
    idx = np.flatnonzero((want != 0) & (sign == want))
    _, pick = np.unique(group[idx], return_index=True)
    f = f[np.sort(idx[pick])]
    used = np.zeros(len(uniq), dtype=bool)
    used[f.reshape(-1)] = True
    remap = np.cumsum(used) - 1
    return uniq[used], remap[f].astype(np.int64)


def clean_mesh(mesh: Mesh, *, weld: bool = True) -> Mesh:
    """Remove degenerate, duplicate and cancelling faces and unused vertices.

    Parameters
    ----------
    mesh : Mesh
    weld : bool, optional
        Also merge vertices with bitwise-identical coordinates (right after
        marching cubes; not after a simplification, where coincident but
        distinct vertices must stay distinct).

    Returns
    -------
    Mesh
        A new mesh: no face repeats a vertex; of several faces on the same
        vertex set, opposite orientations cancel in pairs and one face of
        the remaining orientation (if any) is kept; vertices no face uses are
        dropped (indices renumbered in order).
    """
    _check_mesh(mesh)
    v, f = _clean(mesh.vertices, mesh.faces, weld=weld)
    return Mesh(v, f)


def orient_outward(mesh: Mesh) -> Mesh:
    """Flip every face if the signed volume is negative.

    The faces of a consistently oriented closed mesh either all point
    outward (positive :func:`mesh_volume_mm3`) or all inward; this restores
    the former. Per-component orientation is not changed otherwise.

    Parameters
    ----------
    mesh : Mesh

    Returns
    -------
    Mesh
        ``mesh`` itself when already outward, else a new mesh with the
        winding of every face reversed.
    """
    _check_mesh(mesh)
    if _signed_volume(mesh.vertices, mesh.faces) >= 0:
        return mesh
    return Mesh(mesh.vertices, mesh.faces[:, ::-1])


# ---------------------------------------------------------------------------
# marching cubes
# ---------------------------------------------------------------------------


def extract_surface(
    mask: np.ndarray,
    affine: np.ndarray,
    *,
    level: float = 0.5,
    padding: int = 1,
) -> Mesh:
    """Extract the closed, outward-oriented surface of a binary mask.

    Steps (spec section 5):

    1. crop the mask to the bounding box of its voxels and zero-pad it by
       ``padding`` voxels on every side, so that objects touching the array
       border still give closed surfaces ([A15]);
    2. run marching cubes at ``level`` in voxel-index space
       (``skimage.measure.marching_cubes(V, level, method='lewiner',
       allow_degenerate=False)``, [A16]; never the hole-prone
       ``'lorensen'`` table);
    3. undo the crop and padding offsets and map the ``(z, y, x)`` indices to
       RAS mm with :func:`tumor3d.imaging.scan.zyx_index_to_ras`, so anisotropic
       spacing, rotations and flips of the affine are honoured exactly;
    4. weld identical vertices, drop degenerate and duplicate faces;
    5. orient the faces outward (counter-clockwise seen from outside:
       positive signed volume). The index-to-RAS map reverses the axis order
       and may have a negative determinant, each of which flips the winding;
       the orientation is fixed once, globally, from the signed volume.

    Parameters
    ----------
    mask : ndarray of bool or integer 0/1, shape (z, y, x)
        The tumour mask on the (possibly interpolated) voxel grid.
    affine : (4, 4) ndarray
        Maps the voxel index ``(x, y, z, 1)`` to RAS mm.
    level : float, optional
        Iso-value in (0, 1); 0.5 puts the surface half way between voxel
        centres inside and outside.
    padding : int, optional
        Zero padding in voxels on every side, at least 1.

    Returns
    -------
    Mesh
        Vertices in RAS mm, faces counter-clockwise seen from outside.

    Raises
    ------
    InputError
        On a mask that is not 3-D 0/1, a bad affine, level or padding.
    NoSurfaceError
        If the mask holds no voxel.

    Examples
    --------
    >>> m = np.zeros((3, 3, 3), dtype=bool)
    >>> m[1, 1, 1] = True
    >>> mesh = extract_surface(m, np.diag([2.0, 2.0, 2.0, 1.0]))
    >>> mesh.n_faces, round(mesh_volume_mm3(mesh), 3)
    (8, 1.333)
    """
    m = _check_binary_mask(mask)
    aff = _check_affine(affine)
    if isinstance(level, bool) or not isinstance(level, (int, float, np.floating, np.integer)):
        raise InputError(f"level must be a number in (0, 1), got {level!r}")
    if not 0.0 < float(level) < 1.0:
        raise InputError(f"level must lie strictly between 0 and 1, got {level}")
    if isinstance(padding, bool) or not isinstance(padding, (int, np.integer)) or padding < 1:
        raise InputError(f"padding must be an integer >= 1 voxel, got {padding!r}")
    if not m.any():
        raise NoSurfaceError("the mask holds no voxel: there is no surface to extract")

    # bounding box from the three axis projections (much cheaper than np.nonzero)
    lo = np.zeros(3, dtype=np.int64)
    hi = np.zeros(3, dtype=np.int64)
    for axis in range(3):
        occupied = np.flatnonzero(m.any(axis=tuple(k for k in range(3) if k != axis)))
        lo[axis] = occupied[0]
        hi[axis] = occupied[-1] + 1
    crop = m[lo[0] : hi[0], lo[1] : hi[1], lo[2] : hi[2]]
    volume = np.pad(crop.astype(np.float32), int(padding), mode="constant")
    verts, faces, _, _ = marching_cubes(
        volume, float(level), method="lewiner", allow_degenerate=False
    )
    verts_idx = verts.astype(np.float64) + (lo - int(padding))
    verts_idx, faces = _clean(verts_idx, faces.astype(np.int64))
    if len(faces) == 0:  # pragma: no cover - a non-empty padded mask always has faces
        raise NoSurfaceError("marching cubes produced no triangle")
    vertices = zyx_index_to_ras(verts_idx, aff)
    if _signed_volume(vertices, faces) < 0:
        faces = faces[:, ::-1].copy()
    return Mesh(vertices, faces)
