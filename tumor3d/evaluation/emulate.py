r"""Thick-slice emulation of a thin-slice (e.g. 1 mm) volume.

The paper's scans have 2 mm slices every 5 mm. From a thin volume with slice
step ``s`` (mm) along ``axis``, :func:`emulate_thick_slices` builds one thick
slice every ``step_mm``, each the mean of the thin slices covering
``thickness_mm``:

.. math::

    k = \mathrm{step}/s, \quad m = \mathrm{thickness}/s, \quad
    T_j = \frac{1}{m} \sum_{i=o + jk}^{o + jk + m - 1} S_i,
    \qquad j = 0, \dots, n - 1, \quad n = \lfloor (Z - o - m) / k \rfloor + 1

with ``S_i`` the thin slices (``i = 0 .. Z-1`` along ``axis``) and ``o`` the
index of the first thin slice used (``offset``, default 0). So thick slice
``j`` is formed by thin slices ``o + jk, ..., o + jk + m - 1``
(:attr:`ThickSlices.thin_indices`); thin slices after the last complete
thick slice are dropped. Both ``k`` and ``m`` must be whole numbers (within
0.1 %), ``1 <= m <= k``.

Geometry: the thick slice's centre is the mean position of its thin slices,
thin index ``c_j = o + jk + (m - 1)/2``; the new affine maps thick index
``j`` to the world position of thin index ``c_j`` (its slice column is ``k``
times the thin one, its origin moves to ``c_0``). The slice thickness is
``m s`` and the gap ``(k - m) s`` (``step = thickness + gap``).

Labels (:func:`emulate_thick_labels`): tumour on thick slice ``j`` where the
mean of the binary reference over the same thin slices is ``>= 0.5`` (with
``m = 2``: tumour on at least one of the two).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from tumor3d.errors import InputError

__all__ = ["ThickSlices", "emulate_thick_labels", "emulate_thick_slices", "thick_slice_plan"]

_REL_TOL = 1e-3


@dataclass(frozen=True)
class ThickSlices:
    """An emulated thick-slice volume.

    Parameters
    ----------
    volume : ndarray
        The thick-slice volume, same axis order as the input, ``n`` slices
        along ``axis`` (float32 for images, bool for labels).
    affine : (4, 4) ndarray
        Voxel index (array axis order) -> world mm.
    axis : int
        The slice axis.
    step_mm, thickness_mm, gap_mm : float
        Centre-to-centre slice step, slice thickness, and gap (mm).
    thin_indices : (n, m) int ndarray
        ``thin_indices[j]`` = the thin slices averaged into thick slice ``j``.
    """

    volume: np.ndarray
    affine: np.ndarray
    axis: int
    step_mm: float
    thickness_mm: float
    gap_mm: float
    thin_indices: np.ndarray


def thick_slice_plan(
    n_thin: int,
    thin_step_mm: float,
    *,
    step_mm: float,
    thickness_mm: float,
    offset: int = 0,
) -> np.ndarray:
    """Which thin slices form each thick slice (see the module docstring).

    Parameters
    ----------
    n_thin : int
        Number of thin slices ``Z`` (>= 1).
    thin_step_mm : float
        Thin slice step ``s`` in mm.
    step_mm, thickness_mm : float
        Thick slice step and thickness in mm.
    offset : int, default 0
        First thin slice used, ``0 <= offset``.

    Returns
    -------
    (n, m) int ndarray
        Row ``j`` = ``o + jk + [0, 1, ..., m-1]``.

    Raises
    ------
    InputError
        If the step is smaller than the thin step (the slices are already
        thicker than the requested step), step or thickness is not a whole
        multiple of the thin step, the thickness exceeds the step, or fewer
        than 2 thick slices fit.
    """
    s = _positive(thin_step_mm, "thin_step_mm")
    step = _positive(step_mm, "step_mm")
    thick = _positive(thickness_mm, "thickness_mm")
    if isinstance(n_thin, bool) or not isinstance(n_thin, int | np.integer) or n_thin < 1:
        raise InputError(f"n_thin must be a positive integer, got {n_thin!r}")
    if isinstance(offset, bool) or not isinstance(offset, int | np.integer) or offset < 0:
        raise InputError(f"offset must be an integer >= 0, got {offset!r}")
    if step < s * (1 - _REL_TOL):
        raise InputError(
            f"emulate_step_mm = {step:g} mm is smaller than the image's own slice step "
            f"{s:.4g} mm: its slices are already thicker than the requested step"
        )
    k = _whole(step / s, f"emulate_step_mm = {step:g} mm", s)
    m = _whole(thick / s, f"emulate_thickness_mm = {thick:g} mm", s)
    if m > k:
        raise InputError(
            f"emulate_thickness_mm = {thick:g} mm exceeds emulate_step_mm = {step:g} mm "
            "(slices would overlap)"
        )
    n = (int(n_thin) - int(offset) - m) // k + 1 if n_thin - offset >= m else 0
    if n < 2:
        raise InputError(
            f"only {max(n, 0)} thick slice(s) of {thick:g} mm every {step:g} mm fit in "
            f"{n_thin} thin slices of {s:.4g} mm (offset {offset}): at least 2 are needed"
        )
    return offset + k * np.arange(n)[:, None] + np.arange(m)[None, :]


def emulate_thick_slices(
    volume: np.ndarray,
    affine: object,
    *,
    axis: int,
    step_mm: float,
    thickness_mm: float,
    offset: int = 0,
) -> ThickSlices:
    """Resample a thin-slice image to thick slices (mean over the thickness).

    Parameters
    ----------
    volume : 3-D ndarray of numbers
        The thin-slice image in its own axis order (e.g. a NIfTI's array).
    affine : (4, 4) array_like
        Voxel index ``(i0, i1, i2, 1)`` in array axis order -> world mm.
    axis : int
        The slice axis (0, 1 or 2); its step is the norm of that affine column.
    step_mm, thickness_mm : float
        Thick slice step (centre to centre) and thickness in mm.
    offset : int, default 0
        First thin slice used.

    Returns
    -------
    ThickSlices
        ``volume`` float32; slice ``j`` = mean of ``thin_indices[j]``.
        The input is not modified.
    """
    v, aff, ax = _check_volume(volume, affine, axis)
    if not np.issubdtype(v.dtype, np.number) or np.issubdtype(v.dtype, np.complexfloating):
        raise TypeError(f"volume must be a real numeric array, got dtype {v.dtype}")
    plan, s = _plan_for(v, aff, ax, step_mm, thickness_mm, offset)
    moved = np.moveaxis(v, ax, 0).astype(np.float64, copy=False)
    thick = moved[plan].mean(axis=1)  # (n, ...) : mean over each row of thin slices
    return _result(np.moveaxis(thick, 0, ax).astype(np.float32), aff, ax, plan, s)


def emulate_thick_labels(
    mask: np.ndarray,
    affine: object,
    *,
    axis: int,
    step_mm: float,
    thickness_mm: float,
    offset: int = 0,
) -> ThickSlices:
    """Resample a thin binary label the same way: tumour where the mean is >= 0.5.

    Parameters
    ----------
    mask : 3-D ndarray of bool (or 0/1)
    affine, axis, step_mm, thickness_mm, offset
        As for :func:`emulate_thick_slices`.

    Returns
    -------
    ThickSlices
        ``volume`` bool.
    """
    m, aff, ax = _check_volume(mask, affine, axis)
    if m.dtype != bool:
        if not np.all(np.isin(m, (0, 1))):
            raise InputError("mask must be binary (only 0 and 1)")
        m = m.astype(bool)
    plan, s = _plan_for(m, aff, ax, step_mm, thickness_mm, offset)
    frac = np.moveaxis(m, ax, 0)[plan].mean(axis=1)
    return _result(np.moveaxis(frac >= 0.5, 0, ax), aff, ax, plan, s)


def _check_volume(volume: object, affine: object, axis: object) -> tuple:
    if not isinstance(volume, np.ndarray):
        raise TypeError(f"volume must be a numpy array, got {type(volume).__name__}")
    if volume.ndim != 3:
        raise InputError(f"volume must be 3-D, got shape {volume.shape}")
    aff = np.asarray(affine, dtype=np.float64)
    if aff.shape != (4, 4) or not np.all(np.isfinite(aff)):
        raise InputError(f"affine must be a finite 4x4 matrix, got shape {aff.shape}")
    if isinstance(axis, bool) or not isinstance(axis, int | np.integer) or not 0 <= axis <= 2:
        raise InputError(f"axis must be 0, 1 or 2, got {axis!r}")
    return volume, aff, int(axis)


def _plan_for(v, aff, ax, step_mm, thickness_mm, offset) -> tuple[np.ndarray, float]:
    s = float(np.linalg.norm(aff[:3, ax]))
    plan = thick_slice_plan(
        v.shape[ax], s, step_mm=step_mm, thickness_mm=thickness_mm, offset=offset
    )
    return plan, s


def _result(vol: np.ndarray, aff: np.ndarray, ax: int, plan: np.ndarray, s: float) -> ThickSlices:
    k = int(plan[1, 0] - plan[0, 0])
    m = int(plan.shape[1])
    new = aff.copy()
    centre0 = float(plan[0, 0]) + (m - 1) / 2.0
    new[:3, 3] = aff[:3, 3] + centre0 * aff[:3, ax]
    new[:3, ax] = k * aff[:3, ax]
    plan = plan.copy()
    plan.setflags(write=False)
    return ThickSlices(
        volume=vol,
        affine=new,
        axis=ax,
        step_mm=k * s,
        thickness_mm=m * s,
        gap_mm=(k - m) * s,
        thin_indices=plan,
    )


def _positive(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise TypeError(f"{name} must be a number of mm, got {value!r}")
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise InputError(f"{name} must be a positive finite number of mm, got {value!r}")
    return v


def _whole(ratio: float, what: str, s: float) -> int:
    k = round(ratio)
    if k < 1 or abs(ratio - k) > _REL_TOL * max(k, 1):
        raise InputError(f"{what} is not a whole multiple of the image's slice step {s:.4g} mm")
    return int(k)
