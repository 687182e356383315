"""Input checks and array preparation shared by the engine-based simplifiers."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tumor3d.errors import InputError
from tumor3d.geometry.mesh import Mesh
from tumor3d.geometry.surface import edge_manifold_report
from tumor3d.simplify import _engine

__all__ = ["CollapseTolerances", "EngineInput", "check_target", "prepare"]


@dataclass(frozen=True)
class CollapseTolerances:
    """Validity thresholds of the collapse engine (not in the paper, spec [A21]).

    Attributes
    ----------
    min_quality : float
        A changed face may not end with ``S(t') < min_quality`` (Eq. 5) unless
        it was already at least that poor before: no new needles. 0.1 is a
        triangle with one angle near 10 degrees; marching-cubes faces of
        binary masks have ``S >= 0.6`` (measured), so the rule only stops
        degeneration.
    max_star : int
        Largest number of faces around a vertex a collapse may create
        (bounds the valence and the scratch buffers); marching-cubes vertices
        have at most 12.
    """

    min_quality: float = 0.1
    max_star: int = 64


DEFAULT_TOLERANCES = CollapseTolerances()


@dataclass(frozen=True)
class EngineInput:
    """Writable copies of a mesh for the engine, with its adjacency and vertex status."""

    vertices: np.ndarray
    faces: np.ndarray
    head: np.ndarray
    nxt: np.ndarray
    status: np.ndarray

    @property
    def n_pinched(self) -> int:
        """Number of vertices where several closed fans meet (locked)."""
        return int(np.count_nonzero(self.status == _engine.STATUS_PINCH))


def check_target(mesh: Mesh, target_faces: int) -> int:
    """Validate ``mesh`` and ``target_faces`` (``1 <= target <= F0``)."""
    if not isinstance(mesh, Mesh):
        raise InputError(f"mesh must be a tumor3d.geometry.mesh.Mesh, got {type(mesh).__name__}")
    if isinstance(target_faces, bool) or not isinstance(target_faces, (int, np.integer)):
        raise InputError(f"target_faces must be an integer, got {target_faces!r}")
    if not 1 <= target_faces <= mesh.n_faces:
        raise InputError(
            f"target_faces must lie in [1, {mesh.n_faces}] (the input's face count), "
            f"got {target_faces}"
        )
    return int(target_faces)


# The most faces whose corner indices (3 per face) fit in int32.
MAX_COMPACT_FACES = (np.iinfo(np.int32).max - 1) // 3


def prepare(mesh: Mesh, method: str, *, compact_index: bool = False) -> EngineInput:
    """Copy the mesh into engine arrays and check it is a closed oriented 2-manifold.

    With ``compact_index`` the index arrays (faces, corner lists) are int32
    (half the bytes of int64, which they are otherwise); every corner index
    must then fit in int32 (at most ``MAX_COMPACT_FACES`` faces).

    Raises
    ------
    InputError
        With ``compact_index``, if the mesh has more than ``MAX_COMPACT_FACES``
        faces.
    InputError
        If any edge is a boundary edge, is shared by more than two faces or
        by two faces in the same direction, or a face repeats a vertex. A
        vertex where several closed fans meet (a pinch) is accepted and
        locked: it is never removed and never kept by a collapse.
    """
    if compact_index and len(mesh.faces) > MAX_COMPACT_FACES:
        raise InputError(
            f"simplification method {method!r} indexes corners in int32: this mesh has "
            f"{len(mesh.faces):,} faces, more than {MAX_COMPACT_FACES:,} "
            "(use method='qem', or a coarser mesh)"
        )
    vertices = np.array(mesh.vertices, dtype=np.float64, order="C")
    faces = np.array(mesh.faces, dtype=np.int32 if compact_index else np.int64, order="C")
    head, nxt = _engine.build_corner_lists(faces, len(vertices))
    status = _engine.vertex_status(faces, len(vertices), head.copy(), nxt.copy())
    if np.any(status == _engine.STATUS_DEFECT):
        r = edge_manifold_report(mesh)
        raise InputError(
            f"simplification method {method!r} needs a closed, consistently oriented "
            f"2-manifold mesh; this one has {r['n_boundary_edges']} boundary, "
            f"{r['n_nonmanifold_edges']} non-manifold and {r['n_inconsistent_edges']} "
            f"inconsistently oriented edges and {r['n_degenerate_faces']} degenerate faces "
            "(clean it with tumor3d.geometry.surface.clean_mesh, or use method='qem')"
        )
    return EngineInput(vertices, faces, head, nxt, status)
