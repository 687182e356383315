"""3-D scores of a reconstruction against the reference.

Private: the evaluation package's metrics may replace them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import ndimage as ndi


def _dice(a: np.ndarray, b: np.ndarray) -> float:
    s = int(a.sum()) + int(b.sum())
    return 1.0 if s == 0 else float(2.0 * np.count_nonzero(a & b) / s)


def _surface(mask: np.ndarray) -> np.ndarray:
    """Object voxels with a 6-neighbour outside the object (the volume border counts as outside)."""
    return mask & ~ndi.binary_erosion(mask, structure=ndi.generate_binary_structure(3, 1))


def _hd95_mm(a: np.ndarray, b: np.ndarray, spacing_mm: Sequence[float]) -> float:
    """95 % Hausdorff distance in mm between the surfaces of two 3-D masks.

    ``max(P95 d(s_a, S_b), P95 d(s_b, S_a))`` over surface voxels ``s`` (the
    robust Hausdorff of the ``surface-distance`` package); ``inf`` if exactly
    one mask is empty, 0 if both are.
    """
    if not a.any() and not b.any():
        return 0.0
    if not a.any() or not b.any():
        return math.inf
    both = a | b
    lo = (
        np.array(
            [
                np.flatnonzero(both.any(axis=tuple(j for j in range(3) if j != i))).min()
                for i in range(3)
            ]
        )
        - 1
    )
    hi = (
        np.array(
            [
                np.flatnonzero(both.any(axis=tuple(j for j in range(3) if j != i))).max()
                for i in range(3)
            ]
        )
        + 2
    )
    lo = np.maximum(lo, 0)
    box = tuple(slice(int(s), int(e)) for s, e in zip(lo, hi, strict=True))
    sa, sb = _surface(a[box]), _surface(b[box])
    d_ab = ndi.distance_transform_edt(~sb, sampling=spacing_mm)[sa]
    d_ba = ndi.distance_transform_edt(~sa, sampling=spacing_mm)[sb]
    return float(max(np.percentile(d_ab, 95), np.percentile(d_ba, 95)))
