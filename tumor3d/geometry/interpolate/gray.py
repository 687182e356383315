"""The gray-level variant (LG): :func:`interpolate_gray_slices` of the preprocessed images."""

from __future__ import annotations

import numbers

import numpy as np

from tumor3d.errors import InputError


def interpolate_gray_slices(images: np.ndarray, *, slices_between: int) -> np.ndarray:
    """Linear gray-level interpolation between acquired slices (the LG baseline, [A14]).

    Fine slice ``j`` of gap ``k`` is ``(1 - t) I_k + t I_{k+1}`` with
    ``t = j / (m + 1)``; acquired slices are copied unchanged. Segmenting the
    returned slices with section 3 gives the paper's LG masks; the same
    layout as :func:`interpolate_stack` makes the two comparable slice by slice.

    Parameters
    ----------
    images : (n, y, x) array_like of float
        Preprocessed gray slices in z order, finite values.
    slices_between : int
        ``m >= 0`` slices to insert per gap.

    Returns
    -------
    (Z, y, x) float64 ndarray
        ``Z = (n - 1)(m + 1) + 1`` slices; fine slice ``j`` lies at acquired
        coordinate ``j / (m + 1)``.

    Raises
    ------
    InputError
        If ``images`` is not a non-empty 3-D array of finite numbers or
        ``slices_between`` is not a non-negative integer.

    Examples
    --------
    >>> interpolate_gray_slices(np.array([[[0.0]], [[4.0]]]), slices_between=3)[:, 0, 0]
    array([0., 1., 2., 3., 4.])
    """
    arr = np.asarray(images)
    if arr.ndim != 3 or arr.size == 0:
        raise InputError(f"images must be a non-empty (n, y, x) array, got shape {arr.shape}")
    if arr.dtype.kind not in "biuf" or not np.all(np.isfinite(arr)):
        raise InputError("images must hold finite numbers")
    if isinstance(slices_between, bool) or not isinstance(slices_between, numbers.Integral):
        raise InputError(f"slices_between must be an integer, got {slices_between!r}")
    m = int(slices_between)
    if m < 0:
        raise InputError(f"slices_between must be >= 0, got {m}")
    f = arr.astype(np.float64)
    step = m + 1
    n = f.shape[0]
    out = np.empty(((n - 1) * step + 1,) + f.shape[1:])
    out[::step] = f
    for j in range(1, step):
        t = j / step
        out[j::step] = (1.0 - t) * f[:-1] + t * f[1:]
    return out
