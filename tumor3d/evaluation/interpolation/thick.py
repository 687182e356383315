"""Thick-slice emulation of a 1 mm label (the every-k-th-slice protocol's input)."""

from __future__ import annotations

import math
import numbers

import numpy as np

from tumor3d.errors import InputError
from tumor3d.geometry.distance import as_mask


def _check_int(value: object, name: str, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral) or int(value) < low:
        raise InputError(f"{name} must be an integer >= {low}, got {value!r}")
    return int(value)


def emulate_thick_labels(
    label_zyx: np.ndarray,
    *,
    step_slices: int,
    thickness_slices: float = 2.0,
    phase: int = 0,
    slab: str = "centred",
) -> tuple[np.ndarray, np.ndarray]:
    """Emulate thick acquired slices from a thin-slice label volume.

    Thin slice ``i`` is the slab ``[i - 1/2, i + 1/2]`` (in thin-slice
    units). Thick slice ``j`` is centred on thin slice ``c_j = phase + j
    step`` and covers ``[c_j - T/2, c_j + T/2]``; its label is tumour where
    the thin labels averaged over that slab, weighted by overlap length, are
    ``>= 1/2``. For ``T = 2`` the weights of thin slices ``c - 1, c, c + 1``
    are ``1/4, 1/2, 1/4`` (times 2 mm). Thin slices beyond the volume do not
    count (the mean is over the part of the slab inside it). Centring the
    thick slices on thin ones puts every fraction ``t = j / step`` of the
    reconstruction on a thin slice of the reference.

    ``slab="flush"`` is the rule of the evaluation flow
    (``tumor3d.evaluation.emulate``): thick slice ``j`` is the plain mean of
    the ``m = T`` whole thin slices ``phase + j step, ..., phase + j step + m -
    1`` (``T`` an integer ``<= step``; thin slices after the last complete
    thick slice are dropped), centred at ``c_j = phase + j step + (m - 1)/2``.
    With ``m = 2`` the label is the union of the two thin labels and the
    centres fall halfway between thin slices.

    Parameters
    ----------
    label_zyx : (z, y, x) array_like of bool
        The reference label on thin slices (1 mm for BraTS).
    step_slices : int
        Slice step ``k >= 1`` in thin slices (5 = the paper's 5 mm step).
    thickness_slices : float
        Slab thickness ``T`` in thin slices, ``0 < T <= 2 step`` (2 = 2 mm).
    phase : int
        Index of the first thick slice's centre (``"flush"``: of its first
        thin slice), ``0 <= phase < step``.
    slab : {"centred", "flush"}
        Where the slab lies, see above.

    Returns
    -------
    thick : (n, y, x) bool ndarray
        The emulated thick-slice labels.
    centres : (n,) float64 ndarray
        ``c_j``, the (thin index) position of each thick slice's centre.

    Raises
    ------
    InputError
        If the label is not a non-empty 3-D binary array or a parameter is
        out of range.

    Examples
    --------
    >>> lab = np.zeros((7, 1, 1), bool); lab[2:4] = True
    >>> thick, c = emulate_thick_labels(lab, step_slices=3)
    >>> c.tolist(), thick[:, 0, 0].tolist()
    ([0.0, 3.0, 6.0], [False, True, False])
    >>> thick, c = emulate_thick_labels(lab, step_slices=3, slab="flush")
    >>> c.tolist(), thick[:, 0, 0].tolist()
    ([0.5, 3.5], [False, True])
    """
    lab = as_mask(label_zyx, "label_zyx", 3)
    k = _check_int(step_slices, "step_slices", 1)
    ph = _check_int(phase, "phase", 0)
    if ph >= k:
        raise InputError(f"phase must be < step_slices = {k}, got {ph}")
    try:
        thick_t = float(thickness_slices)
    except (TypeError, ValueError):
        raise InputError(f"thickness_slices must be a number, got {thickness_slices!r}") from None
    if not (0.0 < thick_t <= 2 * k):
        raise InputError(f"thickness_slices must be in (0, 2 step] = (0, {2 * k}], got {thick_t}")
    n_thin = lab.shape[0]
    if slab == "flush":
        m = round(thick_t)
        if abs(m - thick_t) > 1e-9 or not (1 <= m <= k):
            raise InputError(
                f"slab='flush' needs a whole thickness_slices in [1, step = {k}], got {thick_t}"
            )
        starts = np.arange(ph, n_thin - m + 1, k)
        # the mean of each slab's bool slices (float64), never a float copy of the volume
        flush = np.array([lab[a : a + m].mean(axis=0) >= 0.5 for a in starts], dtype=bool)
        return flush.reshape((len(starts),) + lab.shape[1:]), starts + (m - 1) / 2.0
    if slab != "centred":
        raise InputError(f"slab must be 'centred' or 'flush', got {slab!r}")
    centres = np.arange(ph, n_thin, k, dtype=np.int64)
    out = np.zeros((len(centres),) + lab.shape[1:], dtype=bool)
    half = thick_t / 2.0
    for j, c in enumerate(centres):
        lo, hi = c - half, c + half
        total = np.zeros(lab.shape[1:])
        weight = 0.0
        for i in range(max(0, math.floor(lo + 0.5)), min(n_thin - 1, math.ceil(hi - 0.5)) + 1):
            w = min(hi, i + 0.5) - max(lo, i - 0.5)
            if w > 0:
                total += w * lab[i]
                weight += w
        out[j] = total >= 0.5 * weight - 1e-12
    return out, centres.astype(np.float64)
