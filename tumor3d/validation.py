"""Shared validators of public-function arguments.

Every public function of tumor3d validates its arguments and then hands them
to a private helper that computes. These are the validators they share:
wrong types raise :class:`TypeError`, bad values raise
:class:`tumor3d.errors.InputError` (a :class:`ValueError`), and every message
names the argument (and the file, where given) and the problem.
"""

from __future__ import annotations

import math
import reprlib
from typing import Any

import numpy as np

from tumor3d.constants import MESSAGE_VALUE_CHARS, SINGULAR_DET_TOL
from tumor3d.errors import InputError

__all__ = [
    "check_affine",
    "check_binary_mask",
    "check_int",
    "check_positive",
    "non_finite_problem",
    "short_repr",
]


def non_finite_problem(values: np.ndarray) -> str | None:
    """Why ``values`` cannot be used because of NaN or infinite entries, else None.

    >>> non_finite_problem(np.array([1.0, np.nan, np.inf]))
    '2 of 3 voxel values are not finite (1 NaN, 1 infinite)'
    >>> non_finite_problem(np.arange(3)) is None
    True
    """
    v = np.asarray(values)
    if v.dtype.kind not in "fc":
        return None
    n_bad = int(v.size - np.count_nonzero(np.isfinite(v)))
    if not n_bad:
        return None
    n_nan = int(np.count_nonzero(np.isnan(v)))
    return (
        f"{n_bad} of {v.size} voxel values are not finite ({n_nan} NaN, "
        f"{n_bad - n_nan} infinite)"
    )


def check_positive(
    value: Any,
    name: str,
    *,
    allow_zero: bool = False,
    unit: str = "",
    where: str | None = None,
) -> float:
    """Return ``value`` as a finite float ``> 0`` (or ``>= 0`` with ``allow_zero``).

    Parameters
    ----------
    value : int or float
        The candidate (a bool is refused).
    name : str
        Argument or key name used in the message.
    allow_zero : bool
        Accept 0.
    unit : str
        Unit named in the message, e.g. ``"mm"``.
    where : str, optional
        File or key path prefixed to the message.

    Raises
    ------
    TypeError
        If ``value`` is not a real number and ``where`` is None (a wrong
        argument type is a programming error).
    InputError
        If it is not finite, negative, or zero without ``allow_zero``; also
        for a wrong type when ``where`` names the file it was read from (the
        file's content is user input).

    Examples
    --------
    >>> check_positive(2, "radius_mm")
    2.0
    """
    bound = "a non-negative" if allow_zero else "a positive"
    what = f"{bound} number" + (f" of {unit}" if unit else "")
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        message = f"{name} must be {what}, got {_short(value)}"
        if where is not None:
            raise InputError(message, where)
        raise TypeError(message)
    v = float(value)
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise InputError(f"{name} must be {what}, got {_short(value)}", where)
    return v


def check_int(value: Any, name: str, *, minimum: int, where: str | None = None) -> int:
    """Return ``value`` as an int ``>= minimum``.

    Raises
    ------
    TypeError
        If ``value`` is not an integer (a bool is refused).
    InputError
        If it is below ``minimum``.
    """
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise TypeError(
            (f"{where}: " if where else "")
            + f"{name} must be an integer >= {minimum}, got {_short(value)}"
        )
    if value < minimum:
        raise InputError(f"{name} must be an integer >= {minimum}, got {value!r}", where)
    return int(value)


def check_affine(affine: Any, name: str = "affine", *, where: str | None = None) -> np.ndarray:
    """Return a finite, invertible 4x4 affine as a float64 copy.

    Parameters
    ----------
    affine : (4, 4) array_like
        Voxel index -> world mm; last row ``(0, 0, 0, 1)``.

    Raises
    ------
    TypeError
        If it is not numeric.
    InputError
        Wrong shape, non-finite entries, a last row other than
        ``(0, 0, 0, 1)`` or ``|det| < SINGULAR_DET_TOL``.
    """
    try:
        aff = np.array(affine, dtype=np.float64)
    except (TypeError, ValueError):
        raise TypeError(f"{name} must be a numeric 4x4 array, got {_short(affine)}") from None
    if aff.shape != (4, 4):
        raise InputError(f"{name} must be 4x4, got shape {aff.shape}", where)
    if not np.all(np.isfinite(aff)):
        raise InputError(f"{name} must be finite", where)
    if not np.array_equal(aff[3], [0.0, 0.0, 0.0, 1.0]):
        raise InputError(f"{name}'s last row must be (0, 0, 0, 1), got {aff[3]}", where)
    if abs(np.linalg.det(aff[:3, :3])) < SINGULAR_DET_TOL:
        raise InputError(f"{name} is singular (|det| < {SINGULAR_DET_TOL:g})", where)
    return aff


def check_binary_mask(mask: Any, name: str = "mask", *, ndim: int | None = None) -> np.ndarray:
    """Return a boolean view/copy of a mask whose values are all 0 or 1.

    Parameters
    ----------
    mask : ndarray
        bool, or integers/floats that are all 0 or 1.
    ndim : int, optional
        Required number of dimensions.

    Raises
    ------
    TypeError
        If it is not a numeric or boolean array.
    InputError
        Wrong number of dimensions or values other than 0 and 1.
    """
    arr = np.asarray(mask)
    if arr.dtype.kind not in "biuf":
        raise TypeError(f"{name} must be a boolean or numeric array, got dtype {arr.dtype}")
    if ndim is not None and arr.ndim != ndim:
        raise InputError(f"{name} must be {ndim}-D, got shape {arr.shape}")
    if arr.dtype == bool:
        return arr
    if arr.size and not np.all((arr == 0) | (arr == 1)):
        raise InputError(f"{name} must hold only 0 and 1 (a binary mask)")
    return arr.astype(bool)


def short_repr(value: Any, limit: int = MESSAGE_VALUE_CHARS) -> str:
    """A ``repr`` of ``value`` of at most ``limit`` characters, for error messages.

    Containers are abbreviated while they are rendered (``reprlib``), so a
    huge or deeply nested value (an expanded YAML alias bomb) costs no more
    than a small one.

    Examples
    --------
    >>> short_repr(list(range(10**6)))
    '[0, 1, 2, 3, 4, 5, ...]'
    """
    text = _REPR.repr(value)
    return text if len(text) <= limit else text[: limit - 3] + "..."


_REPR = reprlib.Repr()
_REPR.maxlevel = 3
_REPR.maxlist = _REPR.maxtuple = _REPR.maxset = _REPR.maxdict = 6
_REPR.maxstring = _REPR.maxother = MESSAGE_VALUE_CHARS
_short = short_repr
