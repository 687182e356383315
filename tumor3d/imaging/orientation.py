"""The working orientation: which way a scan's axes run, and how to make them so.

The readers reverse the Scan axes that run against the working orientation
(:func:`canonical_flips`, :func:`canonical_orientation`): ``x`` towards the
patient's left, rows (``y``) towards posterior on an axial slice and towards
inferior on a coronal or sagittal one, slices (``z``) towards superior on an
axial stack (left on a sagittal one, posterior on a coronal one). This is how
DICOM and the BraTS volumes store an axial head (LPS), and so how the learned
method's training scans ran: its position features and its U-Net read an
array, and a patient stored the other way (a LAS NIfTI, slices from the top
down) would otherwise be another input to them (one BraTS FLAIR stored LAS
lost 16 % of its learned volume).

Axes are only reversed (:func:`~tumor3d.imaging.affine.reverse_axes`), never
resampled; the :class:`~tumor3d.imaging.scan.SourceGrid` records the reversal, and
:func:`slice_order_note` says so where it changes the slice numbers.
"""

from __future__ import annotations

from dataclasses import replace
from typing import TYPE_CHECKING

import numpy as np

from tumor3d.imaging.affine import reverse_axes

if TYPE_CHECKING:  # the data model imports this module (tumor3d.imaging.scan re-exports it)
    from tumor3d.imaging.scan import Scan, SourceGrid

__all__ = ["canonical_flips", "canonical_orientation", "slice_order_note"]


def canonical_flips(affine: np.ndarray) -> tuple[bool, bool, bool]:
    """Which Scan axes ``(x, y, z)`` run against the working orientation.

    Each axis is judged by the RAS direction its affine column is closest to
    (the largest absolute component; a tie goes to the first of R, A, S): an
    axis along left-right should run towards the left, one along front-back
    towards posterior, and one along superior-inferior towards inferior in
    the slice plane (rows run top to bottom) and towards superior across
    slices. For an axial head that is LPS, the order of DICOM and of the
    BraTS volumes.

    Parameters
    ----------
    affine : (4, 4) array_like
        Maps the Scan's ``(x, y, z, 1)`` to RAS mm.

    Returns
    -------
    tuple of bool
        ``True`` where that axis should be reversed.

    Examples
    --------
    >>> canonical_flips(np.diag([-1.0, -1.0, 5.0, 1.0]))  # LPS
    (False, False, False)
    >>> canonical_flips(np.diag([-1.0, 1.0, -5.0, 1.0]))  # LAI
    (False, True, True)
    >>> canonical_flips(np.eye(4)[:, [0, 2, 1, 3]])  # coronal RSA: x to R, rows to S
    (True, True, True)
    """
    cols = np.asarray(affine, dtype=np.float64)[:3, :3]
    units = cols / np.linalg.norm(cols, axis=0)
    flips = []
    for k in range(3):
        u = units[:, k]
        d = int(np.argmax(np.round(np.abs(u), 9)))
        wanted = 1.0 if (d == 2 and k == 2) else -1.0  # S across slices; L, P, I otherwise
        flips.append(bool(u[d] * wanted < 0))
    return flips[0], flips[1], flips[2]


def canonical_orientation(scan: Scan) -> Scan:
    """The same scan with its axes run as the working orientation (see the module docstring).

    Axes are only reversed (:func:`canonical_flips`); voxels keep their values
    and world positions, and the source grid records the reversal, so outputs
    are still written in the input's own voxel order. A scan already in the
    working orientation is returned as it is.
    """
    flips = canonical_flips(scan.affine)
    if not any(flips):
        return scan
    image, affine = reverse_axes(scan.image, scan.affine, flips)
    grid = scan.source_grid
    combined = tuple(a != b for a, b in zip(grid.flips, flips, strict=True))
    return replace(
        scan,
        image=np.ascontiguousarray(image),
        affine=affine,
        source_grid=replace(grid, flips=combined),
    )


def slice_order_note(grid: SourceGrid) -> str | None:
    """A note for a file that stores its slices the other way round (None otherwise).

    The notes, the report and ``slices.parquet``'s ``slice_index`` count slices in the
    working order (inferior to superior on an axial stack); such a file, and a viewer
    showing it, counts them from the other end.

    >>> from tumor3d.imaging.scan import SourceGrid
    >>> flipped = SourceGrid(shape=(4, 4, 31), affine=np.eye(4), flips=(False, False, True))
    >>> slice_order_note(flipped)[:60]
    'slice numbers count from the other end of the file: it store'
    >>> slice_order_note(SourceGrid(shape=(4, 4, 31), affine=np.eye(4))) is None
    True
    """
    if not grid.flips[2]:
        return None
    last = grid.shape[grid.axes[2]] - 1
    return (
        "slice numbers count from the other end of the file: it stores its slices the other "
        f"way round (slice k here is the file's slice {last} - k; slices.parquet has both)"
    )
