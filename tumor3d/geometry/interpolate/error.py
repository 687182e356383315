"""The interpolation error of a method: leave-one-out on the acquired slices."""

from __future__ import annotations

import numbers
from collections.abc import Sequence

import numpy as np

from tumor3d.errors import InputError
from tumor3d.geometry.distance import (
    as_mask,
)
from tumor3d.geometry.interpolate.methods import (
    _DEFAULT_METHOD,
    _DEFAULT_PARTS,
    Method,
    Parts,
    _check_method,
    _check_parts,
    _spacing_or_unit,
)
from tumor3d.geometry.interpolate.pair import _interpolate_gap


def interpolation_error_percent(truth: np.ndarray, estimate: np.ndarray) -> float:
    """Interpolation error of Eq. 10: ``card(S xor S_hat) / card(S) * 100``.

    Parameters
    ----------
    truth : array_like of bool
        The true mask ``S`` (any number of dimensions); must not be empty.
    estimate : array_like of bool
        The interpolated mask ``S_hat``, same shape.

    Returns
    -------
    float
        Percentage of the true area (can exceed 100).

    Raises
    ------
    InputError
        If the shapes differ, an array is not binary, or ``truth`` holds no
        object pixel.

    Examples
    --------
    >>> interpolation_error_percent([[1, 1, 0, 0]], [[0, 1, 1, 0]])
    100.0
    """
    s = np.asarray(truth)
    e = np.asarray(estimate)
    if s.shape != e.shape:
        raise InputError(
            f"truth and estimate must have the same shape, got {s.shape} and {e.shape}"
        )
    s = as_mask(s, "truth", s.ndim)
    e = as_mask(e, "estimate", e.ndim)
    n_true = int(np.count_nonzero(s))
    if n_true == 0:
        raise InputError("truth holds no object pixel: Eq. 10 divides by card(S)")
    return float(100.0 * np.count_nonzero(s ^ e) / n_true)


def leave_one_out_error(
    slice_masks: np.ndarray,
    k: int,
    *,
    method: Method = _DEFAULT_METHOD,
    parts: Parts = _DEFAULT_PARTS,
    pixel_spacing_mm: Sequence[float] | None = None,
) -> float:
    """Eq. 10 error of re-creating acquired slice ``k`` from its neighbours.

    Interpolates ``slice_masks[k - 1]`` and ``slice_masks[k + 1]`` at
    ``t = 1/2`` with :func:`interpolate_pair` and compares the result with
    ``slice_masks[k]`` by :func:`interpolation_error_percent` (Table 4 of [P]).

    Parameters
    ----------
    slice_masks : (n, y, x) array_like of bool
        Acquired slice masks, ``n >= 3``.
    k : int
        Index of the left-out slice, ``1 <= k <= n - 2``.
    method : {"shape-edt", "enhanced", "enhanced-edt", "shape", "linear"}
        Interpolation method.
    parts : {"matched", "whole"}
        See :func:`interpolate_pair`.
    pixel_spacing_mm : (2,) sequence of float, optional
        In-plane spacing for the Euclidean methods.

    Returns
    -------
    float
        The error in percent of the area of slice ``k``.

    Raises
    ------
    InputError
        If ``slice_masks`` is not a non-empty 3-D binary array, ``k`` is
        not an interior slice index, ``method`` or ``parts`` is unknown, or
        slice ``k`` is empty.
    """
    masks = as_mask(slice_masks, "slice_masks", 3)
    n = masks.shape[0]
    if isinstance(k, bool) or not isinstance(k, numbers.Integral) or not (1 <= k <= n - 2):
        raise InputError(f"k must be an integer with 1 <= k <= n - 2 = {n - 2}, got {k!r}")
    meth = _check_method(method)
    prt = _check_parts(parts)
    sp = _spacing_or_unit(pixel_spacing_mm)
    estimate = _interpolate_gap(masks[k - 1], masks[k + 1], [0.5], meth, prt, sp)[0]
    return interpolation_error_percent(masks[k], estimate)
