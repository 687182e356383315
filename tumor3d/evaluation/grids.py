"""Putting two voxel grids of one world space side by side (pure numpy/scipy).

A *grid* is a 3-D array shape and an affine mapping the voxel index
``(i0, i1, i2, 1)`` in array axis order (nibabel's convention) to world mm.
Voxel ``i`` covers ``[i - 1/2, i + 1/2]`` along each axis.

* :func:`world_bounds_mm` -- the axis-aligned world box covered by a grid;
* :func:`grids_overlap` -- whether two grids' boxes intersect;
* :func:`resample_nearest` -- a label/mask on one grid sampled at the voxel
  centres of another (nearest neighbour, 0 outside the source).
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy import ndimage

from tumor3d.errors import InputError

__all__ = ["grids_overlap", "resample_nearest", "same_grid", "voxel_sizes_mm", "world_bounds_mm"]


def _aff(affine: object, name: str) -> np.ndarray:
    a = np.asarray(affine, dtype=np.float64)
    if a.shape != (4, 4) or not np.all(np.isfinite(a)) or abs(np.linalg.det(a[:3, :3])) < 1e-12:
        raise InputError(f"{name} must be a finite, invertible 4x4 affine")
    return a


def _shape(shape: object, name: str) -> tuple[int, int, int]:
    t = tuple(int(s) for s in shape)  # type: ignore[union-attr]
    if len(t) != 3 or min(t) < 1:
        raise InputError(f"{name} must be a 3-D shape of positive sizes, got {shape!r}")
    return t  # type: ignore[return-value]


def voxel_sizes_mm(affine: object) -> np.ndarray:
    """Voxel size along each array axis (norm of each affine column), mm, shape (3,)."""
    return np.linalg.norm(_aff(affine, "affine")[:3, :3], axis=0)


def world_bounds_mm(shape: object, affine: object) -> tuple[np.ndarray, np.ndarray]:
    """World box ``(lo, hi)`` (each (3,), mm) covered by the voxels of a grid."""
    sh = _shape(shape, "shape")
    a = _aff(affine, "affine")
    corners = np.array(
        list(itertools.product(*[(-0.5, n - 0.5) for n in sh])), dtype=np.float64
    )
    pts = corners @ a[:3, :3].T + a[:3, 3]
    return pts.min(axis=0), pts.max(axis=0)


def grids_overlap(shape_a: object, affine_a: object, shape_b: object, affine_b: object) -> bool:
    """Whether the world boxes of two grids intersect (by more than 1e-6 mm per axis)."""
    lo_a, hi_a = world_bounds_mm(shape_a, affine_a)
    lo_b, hi_b = world_bounds_mm(shape_b, affine_b)
    return bool(np.all(np.minimum(hi_a, hi_b) - np.maximum(lo_a, lo_b) > 1e-6))


def same_grid(shape_a: object, affine_a: object, shape_b: object, affine_b: object) -> bool:
    """Whether two grids are identical (equal shapes, affines within 1e-4 mm)."""
    return _shape(shape_a, "shape_a") == _shape(shape_b, "shape_b") and bool(
        np.allclose(_aff(affine_a, "affine_a"), _aff(affine_b, "affine_b"), atol=1e-4)
    )


def resample_nearest(
    source: np.ndarray, source_affine: object, target_shape: object, target_affine: object
) -> np.ndarray:
    """Sample a label volume at the voxel centres of another grid (nearest neighbour).

    Target voxel ``t`` takes the value of the source voxel nearest to the
    world point ``A_t t``, i.e. ``round(A_s^{-1} A_t t)``; 0 where that falls
    outside the source.

    Parameters
    ----------
    source : 3-D ndarray (bool or integer labels)
    source_affine, target_affine : (4, 4) array_like
        Voxel index (array order) -> world mm.
    target_shape : tuple of 3 int

    Returns
    -------
    ndarray of ``source.dtype``, shape ``target_shape``
        A new array (the input is not modified); identical to ``source``
        when the grids are the same.
    """
    if not isinstance(source, np.ndarray):
        raise TypeError(f"source must be a numpy array, got {type(source).__name__}")
    if source.ndim != 3:
        raise InputError(f"source must be 3-D, got shape {source.shape}")
    a_s = _aff(source_affine, "source_affine")
    a_t = _aff(target_affine, "target_affine")
    shape = _shape(target_shape, "target_shape")
    if same_grid(source.shape, a_s, shape, a_t):
        return source.copy()
    m = np.linalg.inv(a_s) @ a_t
    # A one-voxel zero border and mode "nearest": a point rounding into the
    # source takes its voxel, any point beyond takes the zero border (scipy's
    # "constant" mode would also zero the half-voxel rim [-1/2, 0)). The 1e-6
    # voxel shift makes exact half-way points round up everywhere.
    data = np.pad(source.astype(np.uint8) if source.dtype == bool else source, 1)
    out = ndimage.affine_transform(
        data, m[:3, :3], offset=m[:3, 3] + 1.0 + 1e-6, output_shape=shape, order=0,
        mode="nearest",
    )  # fmt: skip
    return out.astype(bool) if source.dtype == bool else out.astype(source.dtype, copy=False)
