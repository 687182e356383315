"""The brain surface: the translucent context around the tumour (spec section 7).

:func:`brain_surface` reconstructs the brain's outer surface from the
thick-slice brain mask of skull removal (the paper reconstructs the brain
surface as well as the tumour); :func:`display_mesh` reduces it to a face
budget for the browser viewer (``viewer.html``), which holds and draws it.
Both are pure (arrays in, :class:`~tumor3d.geometry.mesh.Mesh` out). The
``extract-brain-surface`` stage (``tasks/brain_surface.py``) computes them
once per brain mask, so the renders, ``brain_mesh.ply`` and ``viewer.html``
share one surface and a change of the render settings or of the tumour does
not recompute it.
"""

from __future__ import annotations

import math

import numpy as np

from tumor3d.errors import InputError
from tumor3d.geometry.mesh import Mesh, empty_mesh

__all__ = ["MAX_GRID_VOXELS", "brain_surface", "display_mesh"]

#: The brain surface's grid holds at most this many voxels (4 M: a 2 mm grid over a
#: 32 cm cube; a head's 24 x 24 x 20 cm field of view needs 1.4 M); over a larger extent
#: the grid spacing grows instead (the surface is context for the renders, not measured).
MAX_GRID_VOXELS = 4_000_000


def brain_surface(brain_mask: np.ndarray, affine: np.ndarray, *, spacing_mm: float = 2.0) -> Mesh:
    """The brain surface for rendering, from the (thick-slice) brain mask.

    Shape-based interpolation (Raya and Udupa 1990; the paper reconstructs
    the brain surface too): each acquired slice's mask becomes its in-plane
    signed distance ``d_k`` in mm (negative inside), ``d`` is interpolated
    trilinearly onto an isotropic grid of ``spacing_mm`` covering the same
    extent (coarser where that grid would exceed :data:`MAX_GRID_VOXELS`),
    and the brain is ``{d < 0}``; its surface is
    :func:`tumor3d.geometry.surface.extract_surface` of that grid. At 2 mm a brain
    gives some 30,000-60,000 faces, plenty for a translucent context surface
    and cheap to render. Only the largest connected component is kept. An
    empty slice counts as far outside, so the surface ends flat at the
    first and last slices holding brain (as the paper's reconstruction
    does).

    Parameters
    ----------
    brain_mask : (z, y, x) array_like of bool
        The brain mask on the acquired slices (e.g. ``PreprocessResult.brain_mask``).
    affine : (4, 4) array_like
        Voxel index ``(x, y, z, 1)`` -> RAS mm of that grid.
    spacing_mm : float
        Grid spacing of the surface extraction, in (0.25, 10] mm.

    Returns
    -------
    Mesh
        Closed outward surface in RAS mm; empty (no face) when the mask holds only
        specks narrower than the grid (a brain that was lost: the preprocess stage's
        notes say so).

    Raises
    ------
    InputError
        On a non-3-D or empty mask, a bad affine or spacing.
    """
    from scipy import ndimage as ndi

    from tumor3d.geometry.surface import extract_surface

    mask = np.asarray(brain_mask)
    if mask.ndim != 3 or mask.dtype != bool and not np.isin(mask, (0, 1)).all():
        raise InputError(f"brain_mask must be a (z, y, x) boolean volume, got shape {mask.shape}")
    mask = mask.astype(bool)
    if not mask.any():
        raise InputError("brain_mask is empty: no brain surface to extract")
    aff = np.asarray(affine, dtype=np.float64)
    if (
        aff.shape != (4, 4)
        or not np.all(np.isfinite(aff))
        or abs(np.linalg.det(aff[:3, :3])) < 1e-12
    ):
        raise InputError("affine must be a finite, invertible 4x4 array")
    if isinstance(spacing_mm, bool) or not isinstance(
        spacing_mm, (int, float, np.integer, np.floating)
    ):
        raise InputError(f"spacing_mm must be a number, got {spacing_mm!r}")
    step = float(spacing_mm)
    if not (math.isfinite(step) and 0.25 < step <= 10.0):
        raise InputError(f"spacing_mm must lie in (0.25, 10] mm, got {spacing_mm}")
    labels, n = ndi.label(mask)
    if n > 1:
        mask = labels == 1 + int(np.argmax(np.bincount(labels.ravel())[1:]))
    dx, dy, dz = (float(np.linalg.norm(aff[:3, k])) for k in range(3))
    nz, ny, nx = mask.shape
    half_px = 0.5 * min(dx, dy)  # the mask boundary lies half a pixel outside its pixels
    sd = np.empty(mask.shape, dtype=np.float32)
    for k in range(nz):
        sl = mask[k]
        if not sl.any():
            sd[k] = 1e3  # far outside
            continue
        out = ndi.distance_transform_edt(~sl, sampling=(dy, dx))
        inside = ndi.distance_transform_edt(sl, sampling=(dy, dx))
        sd[k] = np.where(sl, half_px - inside, out - half_px)
    # pad one empty slice at both ends so the surface closes beyond the end slices
    sd = np.concatenate(
        [np.full((1, ny, nx), 1e3, np.float32), sd, np.full((1, ny, nx), 1e3, np.float32)]
    )
    # a context surface only: over an extent larger than a head the grid is coarsened
    # to at most MAX_GRID_VOXELS (readers refuse volumes larger than a scanner images)
    extent_mm3 = (nz + 2) * dz * ny * dy * nx * dx
    step = max(step, (extent_mm3 / MAX_GRID_VOXELS) ** (1.0 / 3.0))
    # new grid: index i along each axis <-> old voxel coordinate i * step / d
    shape_new = [
        max(2, int(np.floor((n_old - 1) * d / step)) + 1)
        for n_old, d in ((nz + 2, dz), (ny, dy), (nx, dx))
    ]
    zz, yy, xx = np.meshgrid(*(np.arange(m) * step for m in shape_new), indexing="ij", sparse=True)
    coords = np.broadcast_arrays(zz / dz, yy / dy, xx / dx)
    fine = ndi.map_coordinates(sd, coords, order=1, mode="nearest") < 0.0
    if not fine.any():  # specks narrower than the grid: nothing a context surface can draw
        return empty_mesh()
    scale = np.diag([step / dx, step / dy, step / dz, 1.0])
    scale[2, 3] = -1.0  # the padded first slice sits at old index -1
    return extract_surface(fine, aff @ scale)


def display_mesh(mesh: Mesh, max_faces: int) -> Mesh:
    """``mesh`` reduced to at most ``max_faces`` faces, for display only.

    Quadric edge collapse (QSlim, :func:`tumor3d.simplify.simplify_mesh` with
    ``method="qem"``, the ``fast-simplification`` package): some 25x faster
    than the volume-exact memoryless collapse on a 37,596-face brain (0.17 s
    against 4.1 s, 8,000 faces), which matters for a context surface that no
    measurement uses; the volume changes by a fraction of a percent, and the
    manifold checks of the other methods are not needed to draw it. A mesh
    already within the budget is returned as is.

    Parameters
    ----------
    mesh : Mesh
        A closed surface (e.g. :func:`brain_surface`).
    max_faces : int
        Face budget, at least 100.

    Returns
    -------
    Mesh

    Raises
    ------
    InputError
        On a non-mesh input or a budget below 100 faces.
    """
    from tumor3d.simplify import simplify_mesh

    if not isinstance(mesh, Mesh):
        raise InputError(f"mesh must be a tumor3d.geometry.mesh.Mesh, got {type(mesh).__name__}")
    if (
        isinstance(max_faces, bool)
        or not isinstance(max_faces, (int, np.integer))
        or max_faces < 100
    ):
        raise InputError(f"max_faces must be an integer >= 100, got {max_faces!r}")
    if mesh.n_faces <= max_faces:
        return mesh
    # P such that floor(F0 * (1 - P/100)) <= max_faces
    percent = 100.0 * (1.0 - max_faces / mesh.n_faces)
    percent = min(99.9, math.ceil(percent * 1000.0) / 1000.0)
    return simplify_mesh(mesh, method="qem", reduction_percent=percent)
