"""Domain rules that join the stages of the method, kept out of the task adapters.

* :func:`tumour_surface` -- the extract-surface stage: an empty tumour mask
  (no tumour found) gives an empty mesh instead of an error, so a tumour-free
  patient completes with volume 0;
* :func:`is_closed_surface` -- a non-empty watertight mesh (an empty mesh
  encloses nothing), the check the surface and simplify stages report.

The Eq. 7 slice rule lives in :func:`tumor3d.metrics.measure_volumes`; the
automatic slice count (``slices_between=None``) in
:func:`tumor3d.geometry.interpolate.interpolate_stack`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from tumor3d.errors import NoSurfaceError
from tumor3d.geometry.mesh import Mesh, empty_mesh
from tumor3d.geometry.surface import extract_surface, is_watertight

__all__ = ["empty_mesh", "is_closed_surface", "tumour_surface"]


def tumour_surface(mask: np.ndarray, affine: np.ndarray, **options: Any) -> Mesh:
    """The closed surface of a tumour mask, or an empty mesh when the mask is empty.

    Parameters
    ----------
    mask : (z, y, x) ndarray of bool
        The interpolated tumour mask.
    affine : (4, 4) ndarray
        ``(x, y, z, 1)`` -> RAS mm.
    **options
        Passed to :func:`tumor3d.geometry.surface.extract_surface` (``level``,
        ``padding``, ...; :class:`~tumor3d.config.SurfaceConfig`).

    Returns
    -------
    Mesh
        RAS mm; empty (0 faces) when ``mask`` holds no voxel.

    Examples
    --------
    >>> tumour_surface(np.zeros((2, 3, 3), bool), np.eye(4)).is_empty
    True
    """
    try:
        return extract_surface(mask, affine, **options)
    except NoSurfaceError:
        if np.any(mask):  # a non-empty mask without surface is a real failure
            raise
        return empty_mesh()


def is_closed_surface(mesh: Mesh) -> bool:
    """True for a non-empty watertight mesh (see :func:`tumor3d.geometry.surface.is_watertight`).

    Examples
    --------
    >>> is_closed_surface(empty_mesh())
    False
    """
    if not isinstance(mesh, Mesh):
        raise TypeError(f"mesh must be a tumor3d.geometry.mesh.Mesh, got {type(mesh).__name__}")
    return bool(not mesh.is_empty and is_watertight(mesh))
