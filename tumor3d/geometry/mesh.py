"""The `Mesh` data model: a triangle surface in RAS millimetres."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tumor3d.errors import MeshError

__all__ = ["Mesh", "empty_mesh"]


@dataclass(frozen=True, eq=False)
class Mesh:
    """A triangle mesh.

    Parameters
    ----------
    vertices : (n, 3) float64 ndarray
        Vertex positions in RAS millimetres.
    faces : (m, 3) int64 ndarray
        Vertex indices of each triangle, counter-clockwise seen from outside
        (outward normals by the right-hand rule).

    Both arrays are copied and made read-only.
    """

    vertices: np.ndarray
    faces: np.ndarray

    def __post_init__(self) -> None:
        v = (
            np.array(self.vertices, dtype=np.float64).reshape(-1, 3)
            if np.size(self.vertices)
            else np.zeros((0, 3))
        )
        f = (
            np.array(self.faces, dtype=np.int64).reshape(-1, 3)
            if np.size(self.faces)
            else np.zeros((0, 3), dtype=np.int64)
        )
        if not np.all(np.isfinite(v)):
            raise MeshError("mesh vertices must be finite")
        if f.size and (f.min() < 0 or f.max() >= len(v)):
            raise MeshError(f"face indices must lie in [0, {len(v)}), got [{f.min()}, {f.max()}]")
        v.setflags(write=False)
        f.setflags(write=False)
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f)

    @property
    def n_vertices(self) -> int:
        """Number of vertices."""
        return int(len(self.vertices))

    @property
    def n_faces(self) -> int:
        """Number of triangles."""
        return int(len(self.faces))

    @property
    def is_empty(self) -> bool:
        """True when the mesh has no faces."""
        return self.n_faces == 0


def empty_mesh() -> Mesh:
    """A mesh with no vertex and no face ("no tumour found", a brain too small to draw).

    >>> empty_mesh().n_faces
    0
    """
    return Mesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
