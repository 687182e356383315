"""Geometry of a voxel grid's affine: slice spacing, shear, slab height, world points.

The functions here read a 4x4 affine only (no image): :func:`slice_plane_spacing_mm`
and :func:`in_plane_shear` (what a :class:`~tumor3d.imaging.scan.Scan` checks its
stated spacings against), :func:`slab_height_mm` (Eq. 7), :func:`zyx_index_to_ras`
(array-order voxel indices to RAS mm) and :func:`reverse_axes` (a grid with some axes
reversed, every voxel kept at its world position).

Affine convention
-----------------
A `Scan`'s affine is 4x4 and maps the voxel index ``(x, y, z, 1)`` to RAS
millimetres, i.e. the affine nibabel would report for the array
``image.transpose(2, 1, 0)``. Use :func:`zyx_index_to_ras` to map points
given in array order ``(z, y, x)``.

Sheared grids
-------------
The slice-axis column of the affine need not be perpendicular to the slice
plane (a NIfTI converted from a gantry-tilted series has such a shear). The
slice *step* is then the distance between slice planes, not the length of
that column: with ``c_x, c_y, c_z`` the affine's first three columns,

    step = |det [c_x c_y c_z]| / |c_x x c_y|

(:func:`slice_plane_spacing_mm`), so that one pixel area times the step is
the voxel volume ``|det|`` and the slab volumes of Eq. 7 add up to the
voxel-counted volume. The two in-plane columns must be perpendicular (to
:data:`tumor3d.constants.IN_PLANE_ORTHOGONALITY_TOL`), so that the pixel area
is ``dx * dy``.
"""

from __future__ import annotations

import numpy as np

from tumor3d.constants import SHEAR_TOL, SINGULAR_DET_TOL
from tumor3d.errors import InputError

__all__ = [
    "in_plane_shear",
    "reverse_axes",
    "slab_height_mm",
    "slice_overlap_note",
    "slice_plane_spacing_mm",
    "zyx_index_to_ras",
]


def slab_height_mm(
    slice_step_mm: float, slice_thickness_mm: float, slice_gap_mm: float | None
) -> float:
    """Slab height of Eq. 7: thickness + gap, or the step where the gap is unknown.

    Parameters
    ----------
    slice_step_mm : float
        Distance between consecutive slice *planes* in mm (for a sheared
        grid: :func:`slice_plane_spacing_mm`, never the slice-axis column's
        length). ``Scan.slice_step_mm`` always is.
    slice_thickness_mm : float
        Nominal slice thickness in mm.
    slice_gap_mm : float or None
        Gap between slices in mm, ``None`` if unknown.

    Returns
    -------
    float
        ``slice_thickness_mm + slice_gap_mm``, or ``slice_step_mm`` when the
        gap is unknown, in mm.
    """
    if slice_gap_mm is None:
        return float(slice_step_mm)
    return float(slice_thickness_mm + slice_gap_mm)


def slice_overlap_note(
    slice_step_mm: float, slice_thickness_mm: float, slice_gap_mm: float | None
) -> str | None:
    """A note for slices thicker than their step (a negative gap), None otherwise.

    Overlapping slices are accepted whatever states their thickness (the option
    or the file's metadata); Eq. 7 then sums each slice's area over one step, so
    no tissue is counted twice, and the note says so.

    >>> slice_overlap_note(5.0, 6.0, -1.0).split(";")[0]
    'the slices overlap: 6 mm thick every 5 mm (1 mm shared by neighbours)'
    >>> slice_overlap_note(5.0, 2.0, 3.0) is None
    True
    """
    if slice_gap_mm is None or slice_gap_mm >= -1e-6 * slice_step_mm:
        return None
    return (
        f"the slices overlap: {slice_thickness_mm:.4g} mm thick every {slice_step_mm:.4g} mm "
        f"({-slice_gap_mm:.4g} mm shared by neighbours); Eq. 7 sums each over its "
        f"{slice_step_mm:.4g} mm step"
    )


def slice_plane_spacing_mm(affine: np.ndarray, slice_axis: int = 2) -> float:
    """Distance between consecutive slice planes of a voxel grid, in mm.

    The slice-axis column ``c_s`` projected on the unit normal of the plane
    spanned by the two other columns ``c_a, c_b``:

        spacing = |c_s . (c_a x c_b)| / |c_a x c_b| = |det A| / |c_a x c_b|

    It equals the column length ``|c_s|`` only when the grid is not sheared;
    when the two differ by at most :data:`tumor3d.constants.SHEAR_TOL`
    (relative), the column length is returned, free of round-off.

    Parameters
    ----------
    affine : (4, 4) array_like
        Voxel index -> world mm.
    slice_axis : {0, 1, 2}
        The voxel axis whose step is wanted (2 for a `Scan`'s affine).

    Returns
    -------
    float
        The plane spacing in mm (> 0).

    Raises
    ------
    InputError
        If the affine is not 4x4, not finite, or singular.

    Examples
    --------
    >>> shear = np.array([[1.0, 0, 3, 0], [0, 1, 0, 0], [0, 0, 5, 0], [0, 0, 0, 1]])
    >>> round(slice_plane_spacing_mm(shear), 9)  # the column has length 5.83
    5.0
    """
    lin = _linear_part(affine)
    if slice_axis not in (0, 1, 2):
        raise InputError(f"slice_axis must be 0, 1 or 2, got {slice_axis!r}")
    a, b = (k for k in range(3) if k != slice_axis)
    normal = np.cross(lin[:, a], lin[:, b])
    column = lin[:, slice_axis]
    length = float(np.linalg.norm(column))
    spacing = abs(float(column @ normal)) / float(np.linalg.norm(normal))
    # Not sheared (to SHEAR_TOL): the column length itself, free of round-off,
    # so an orthogonal grid keeps exactly its stated step.
    return length if length - spacing <= SHEAR_TOL * length else spacing


def in_plane_shear(affine: np.ndarray, slice_axis: int = 2) -> float:
    """How far the two in-plane columns of an affine are from perpendicular.

    Returns ``1 - |c_a x c_b| / (|c_a| |c_b|)`` (0 for perpendicular
    columns; ``1 - sin`` of the angle between them), the relative error of
    ``dx * dy`` as the pixel area.

    Parameters
    ----------
    affine : (4, 4) array_like
        Voxel index -> world mm.
    slice_axis : {0, 1, 2}
        The slice axis; the two others span the slice plane.

    Returns
    -------
    float
        In ``[0, 1)``.
    """
    lin = _linear_part(affine)
    a, b = (k for k in range(3) if k != slice_axis)
    na, nb = np.linalg.norm(lin[:, a]), np.linalg.norm(lin[:, b])
    return float(1.0 - np.linalg.norm(np.cross(lin[:, a], lin[:, b])) / (na * nb))


def _linear_part(affine: np.ndarray) -> np.ndarray:
    aff = np.asarray(affine, dtype=np.float64)
    if aff.shape != (4, 4):
        raise InputError(f"affine must be 4x4, got shape {aff.shape}")
    lin = aff[:3, :3]
    if not np.all(np.isfinite(lin)) or abs(np.linalg.det(lin)) < SINGULAR_DET_TOL:
        raise InputError("affine is singular or not finite")
    return lin


def zyx_index_to_ras(points_zyx: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """Map points given as ``(z, y, x)`` voxel indices to RAS millimetres.

    Parameters
    ----------
    points_zyx : (n, 3) array_like
        Continuous voxel indices in array order ``(z, y, x)``.
    affine : (4, 4) ndarray
        Maps ``(x, y, z, 1)`` to RAS mm (see the module docstring).

    Returns
    -------
    (n, 3) float64 ndarray
        RAS coordinates in millimetres.
    """
    pts = np.asarray(points_zyx, dtype=np.float64).reshape(-1, 3)[:, ::-1]
    aff = np.asarray(affine, dtype=np.float64)
    return pts @ aff[:3, :3].T + aff[:3, 3]


def reverse_axes(
    array_zyx: np.ndarray, affine_xyz: np.ndarray, flips: tuple[bool, bool, bool]
) -> tuple[np.ndarray, np.ndarray]:
    """Reverse some axes of a grid, keeping every voxel at its world position.

    Parameters
    ----------
    array_zyx : ndarray, shape (z, y, x)
    affine_xyz : (4, 4) array_like
        Maps ``(x, y, z, 1)`` of ``array_zyx`` to RAS mm.
    flips : tuple of bool
        Which of ``(x, y, z)`` to reverse.

    Returns
    -------
    array : ndarray, shape (z, y, x)
        A view of ``array_zyx`` with those axes reversed.
    affine : (4, 4) ndarray
        Its affine: a reversed axis' column negated and the origin moved to
        that axis' last voxel.
    """
    arr = np.asarray(array_zyx)
    aff = np.array(affine_xyz, dtype=np.float64)
    for k, flipped in enumerate(flips):
        if flipped:
            arr = np.flip(arr, 2 - k)
            aff[:3, 3] += aff[:3, k] * (arr.shape[2 - k] - 1)
            aff[:3, k] = -aff[:3, k]
    return arr, aff
