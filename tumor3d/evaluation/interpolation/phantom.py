"""A phantom with a drifting tumour: a known 1 mm label whose centroid moves along the slices."""

from __future__ import annotations

import numpy as np


def drifting_tumour_phantom(
    seed: int,
    *,
    shape: tuple[int, int, int] = (80, 112, 112),
    drift_mm_per_mm: tuple[float, float] = (0.35, 0.5),
    n_lobes: int = 3,
    axes_mm: tuple[float, float] = (8.0, 22.0),
) -> np.ndarray:
    """A 1 mm label of a lobed tumour whose cross-section drifts in-plane along z.

    The union of ``n_lobes`` random ellipsoids (semi-axes in ``axes_mm``) around a
    common centre, sheared so the centre of slice ``z`` moves by
    ``drift * (z - z0)`` mm in ``(y, x)`` (the tumour grows obliquely through
    the slices, the case the paper's centroid alignment is made for).

    Parameters
    ----------
    seed : int
        Seed of the random lobes.
    shape : (3,) tuple of int
        ``(z, y, x)`` size in 1 mm voxels.
    drift_mm_per_mm : (2,) tuple of float
        In-plane drift ``(dy/dz, dx/dz)``.
    n_lobes : int
        Number of ellipsoids.
    axes_mm : (2,) tuple of float
        Range of the semi-axes in mm (uniform).

    Returns
    -------
    (z, y, x) bool ndarray
        The label; it does not touch the volume border.
    """
    rng = np.random.default_rng(seed)
    zz, yy, xx = np.meshgrid(*(np.arange(s, dtype=np.float64) for s in shape), indexing="ij")
    c = np.array(shape, dtype=np.float64) / 2.0
    # shear: the tumour's axis runs obliquely through the slices
    yy = yy - drift_mm_per_mm[0] * (zz - c[0])
    xx = xx - drift_mm_per_mm[1] * (zz - c[0])
    out = np.zeros(shape, dtype=bool)
    for _ in range(n_lobes):
        centre = c + rng.uniform(-8, 8, 3)
        axes = rng.uniform(axes_mm[0], axes_mm[1], 3)
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        d = np.stack([zz - centre[0], yy - centre[1], xx - centre[2]], axis=-1) @ q
        out |= ((d / axes) ** 2).sum(axis=-1) <= 1.0
    return out
