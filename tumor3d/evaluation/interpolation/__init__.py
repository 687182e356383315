"""Evaluation of inter-slice interpolation on reference labels (spec section 4, Table 4).

Interpolation error is separate from segmentation error, so these protocols
start from reference labels (expert or phantom), not from the pipeline's
segmentation. Two protocols, both pure (arrays in, rows out):

:func:`table4_rows`
    The paper's Table 4 protocol: of three consecutive acquired slices, the
    outer two ``S_i`` and ``S_{i+2}`` give the estimate of ``S_{i+1}`` at
    ``t = 1/2``, scored by Eq. 10, ``epsilon = card(S xor S_hat) / card(S) x
    100``, for every valid triplet (all three slices hold tumour). Applied to
    the thick-slice stack emulated from a 1 mm label (5 mm step, the
    paper's geometry), so ``S_i`` and ``S_{i+2}`` are 10 mm apart.
:func:`kth_slice_rows`
    A protocol closer to use: keep every ``k``-th slice of a 1 mm reference
    (``k = 3, 5``) with a thickness emulated by :func:`emulate_thick_labels`,
    reconstruct the thin slices between them with each method and score the
    3-D result against the full reference: Dice, the 95 % Hausdorff distance
    in mm and the signed volume error.

Methods are named as in the paper: ``LG`` (linear mask interpolation, the
mask variant of [A14]), ``SO`` (city-block shape-based), ``SE`` (Algorithm
1, chamfer, one centroid per slice), then the variants of this project
(``-EDT``: exact Euclidean distance; ``parts``: matched parts, see
:mod:`tumor3d.geometry.interpolate`) and ``ITK``, the MorphologicalContourInterpolator
of ITK (Zukic et al. 2016, the "fill between slices" of 3D Slicer and
ITK-SNAP), an optional peer (``pip install 'tumor3d[peers]'``).

References
----------
.. [P] V. P. Arakeri and G. R. M. Reddy, "3D reconstruction of brain tumor
   and volume estimation from MR images", IJSIP 6(3), 2013.
.. [Zuk16] D. Zukic, J. Vicory, M. McCormick, L. Wisse, G. Gerig, P.
   Yushkevich and S. Aylward, "ND morphological contour interpolation",
   Insight Journal, 2016. doi:10.54294/achtrg

The package: the two protocols and the ITK peer's call here (they look
:func:`itk_available` up in this namespace), :mod:`~tumor3d.evaluation.interpolation.methods`
(the methods compared, the peer's presence), :mod:`~tumor3d.evaluation.interpolation.thick`
(thick-slice emulation), :mod:`~tumor3d.evaluation.interpolation.scores` (3-D scores) and
:mod:`~tumor3d.evaluation.interpolation.phantom` (a drifting-tumour phantom). The public
names are importable from here.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import numpy as np

from tumor3d.errors import InputError
from tumor3d.evaluation.interpolation.methods import (
    _ITK_HINT,
    ITK_METHOD,
    METHODS,
    _quiet_swig,
    itk_available,
)
from tumor3d.evaluation.interpolation.phantom import drifting_tumour_phantom
from tumor3d.evaluation.interpolation.scores import _dice, _hd95_mm
from tumor3d.evaluation.interpolation.thick import _check_int, emulate_thick_labels
from tumor3d.geometry.distance import as_mask
from tumor3d.geometry.interpolate import (
    interpolate_pair,
    interpolate_stack,
    interpolation_error_percent,
)

__all__ = [
    "ITK_METHOD",
    "METHODS",
    "drifting_tumour_phantom",
    "emulate_thick_labels",
    "itk_available",
    "itk_contour_interpolate",
    "kth_slice_rows",
    "table4_rows",
]


def itk_contour_interpolate(sparse_zyx: np.ndarray) -> np.ndarray:
    """Fill the empty slices between labelled ones with ITK's contour interpolator [Zuk16].

    Runs ``itk.MorphologicalContourInterpolator`` along the slice axis only
    (ITK axis 2 = numpy axis 0), with its defaults (distance-transform based
    median contours, no ball structuring element). Slices that hold tumour
    are kept; ITK does not extrapolate beyond the first and last ones.

    Parameters
    ----------
    sparse_zyx : (z, y, x) array_like of bool
        The stack on the fine grid with only the acquired slices labelled.

    Returns
    -------
    (z, y, x) bool ndarray
        The interpolated stack.

    Raises
    ------
    ImportError
        If the optional ``itk-morphologicalcontourinterpolation`` is missing.
    InputError
        If ``sparse_zyx`` is not a non-empty 3-D binary array.
    """
    mask = as_mask(sparse_zyx, "sparse_zyx", 3)
    if not itk_available():
        raise ImportError(_ITK_HINT)
    with _quiet_swig():
        import itk

        image = itk.image_from_array(np.ascontiguousarray(mask, dtype=np.uint8))
        filt = itk.MorphologicalContourInterpolator.New(image)
        filt.SetAxis(2)
        filt.Update()
        return itk.array_from_image(filt.GetOutput()) > 0


def _resolve_methods(methods: Sequence[str] | None, include_itk: bool) -> list[str]:
    names = list(METHODS) if methods is None else list(methods)
    for name in names:
        if name not in METHODS and name != ITK_METHOD:
            raise InputError(f"unknown method {name!r}: expected one of {[*METHODS, ITK_METHOD]}")
    if include_itk and ITK_METHOD not in names and itk_available():
        names.append(ITK_METHOD)
    if ITK_METHOD in names and not itk_available():
        raise ImportError(_ITK_HINT)
    return names


def table4_rows(
    label_zyx: np.ndarray,
    *,
    case: str,
    step_slices: int = 5,
    thickness_slices: float = 2.0,
    phase: int = 0,
    pixel_spacing_mm: Sequence[float] = (1.0, 1.0),
    methods: Sequence[str] | None = None,
    include_itk: bool = True,
) -> list[dict[str, Any]]:
    """Table 4 of [P] on a reference label: Eq. 10 error of re-creating each middle slice.

    The label is first reduced to thick slices (:func:`emulate_thick_labels`);
    then for every triplet ``i, i + 1, i + 2`` of thick slices that all hold
    tumour, ``S_{i+1}`` is estimated from ``S_i`` and ``S_{i+2}`` at ``t = 1/2``
    and scored by ``epsilon = card(S xor S_hat) / card(S) x 100`` (Eq. 10).

    Parameters
    ----------
    label_zyx : (z, y, x) array_like of bool
        Reference label on thin slices.
    case : str
        Case name copied into every row.
    step_slices, thickness_slices, phase
        Thick-slice emulation, see :func:`emulate_thick_labels`.
    pixel_spacing_mm : (2,) sequence of float
        In-plane spacing for the Euclidean methods.
    methods : sequence of str, optional
        Labels from :data:`METHODS` (and ``"ITK"``); default all of
        :data:`METHODS`.
    include_itk : bool
        Add ITK's interpolator when it is installed.

    Returns
    -------
    list of dict
        One row per triplet and method: ``case``, ``method``, ``slices``
        (``"i-(i+2)"``, 1-based thick indices as the paper counts),
        ``z_thin`` (thin index of the middle slice), ``area_px`` of the true
        middle slice and ``epsilon_percent``. Empty if no triplet is valid.

    Raises
    ------
    InputError
        If the label or a parameter is invalid or a method is unknown.
    ImportError
        If ``"ITK"`` is requested but not installed.
    """
    names = _resolve_methods(methods, include_itk)
    thick, centres = emulate_thick_labels(
        label_zyx, step_slices=step_slices, thickness_slices=thickness_slices, phase=phase
    )
    nonempty = thick.reshape(len(thick), -1).any(axis=1)
    rows: list[dict[str, Any]] = []
    for i in range(len(thick) - 2):
        if not (nonempty[i] and nonempty[i + 1] and nonempty[i + 2]):
            continue
        truth = thick[i + 1]
        for name in names:
            if name == ITK_METHOD:
                sparse = np.zeros((3,) + truth.shape, dtype=bool)
                sparse[0], sparse[2] = thick[i], thick[i + 2]
                estimate = itk_contour_interpolate(sparse)[1]
            else:
                estimate = interpolate_pair(
                    thick[i], thick[i + 2], 0.5, pixel_spacing_mm=pixel_spacing_mm, **METHODS[name]
                )
            rows.append(
                {
                    "case": case,
                    "method": name,
                    "slices": f"{i + 1}-{i + 3}",
                    "z_thin": float(centres[i + 1]),
                    "area_px": int(truth.sum()),
                    "epsilon_percent": interpolation_error_percent(truth, estimate),
                }
            )
    return rows


def _reconstruct(
    thick: np.ndarray,
    centres: np.ndarray,
    n_thin: int,
    name: str,
    *,
    end_caps: str,
    pixel_spacing_mm: Sequence[float],
) -> np.ndarray:
    """Thin-slice reconstruction of a thick-slice label stack with one method.

    Centres on thin slices: ``k - 1`` slices per gap land on the thin grid.
    Centres halfway between thin slices (``slab="flush"``): the stack is
    interpolated to half the thin step (``2k - 1`` per gap) and the fine
    slices on thin positions are kept.
    """
    k = round(centres[1] - centres[0]) if len(centres) > 1 else 1
    frac = float(centres[0] - math.floor(centres[0]))
    sub = 1 if frac == 0.0 else 2  # fine slices per thin slice
    if sub == 2 and abs(frac - 0.5) > 1e-9:
        raise InputError(
            f"thick-slice centres must be whole or half thin indices, got {centres[0]}"
        )
    n_fine = (len(thick) - 1) * k * sub + 1
    if name == ITK_METHOD:
        sparse = np.zeros((n_fine,) + thick.shape[1:], dtype=bool)
        sparse[:: k * sub] = thick
        fine = itk_contour_interpolate(sparse)
    else:
        fine = interpolate_stack(
            thick,
            slices_between=k * sub - 1,
            end_caps=end_caps,  # type: ignore[arg-type]
            pixel_spacing_mm=pixel_spacing_mm,
            **METHODS[name],  # type: ignore[arg-type]
        ).mask
    # fine slice f lies at thin position centres[0] + f / sub
    out = np.zeros((n_thin,) + thick.shape[1:], dtype=bool)
    first = math.ceil(centres[0])
    f0 = round((first - centres[0]) * sub)
    taken = fine[f0::sub]
    out[first : first + len(taken)] = taken[: n_thin - first]
    return out


def kth_slice_rows(
    label_zyx: np.ndarray,
    *,
    case: str,
    spacing_mm: Sequence[float] = (1.0, 1.0, 1.0),
    steps: Sequence[int] = (3, 5),
    thickness_slices: float = 2.0,
    phases: Sequence[int] | None = (0,),
    methods: Sequence[str] | None = None,
    include_itk: bool = True,
    end_caps: Sequence[str] = ("taper",),
    slab: str = "centred",
    extra: Mapping[str, Callable[[np.ndarray, np.ndarray, int], np.ndarray]] | None = None,
) -> list[dict[str, Any]]:
    """Keep every ``k``-th thin slice, reconstruct the rest, score against the full reference.

    For each step ``k`` and phase, :func:`emulate_thick_labels` gives the kept
    slices; each method reconstructs the thin slices between them (``k - 1``
    per gap, so the result lies on the reference grid) and the result is
    compared with the full label: 3-D Dice ``2 |A & B| / (|A| + |B|)``, HD95
    (mm, :func:`_hd95_mm`) and the volume error ``(|A| - |B|) / |B| x 100``
    (signed %, voxel counts).

    Parameters
    ----------
    label_zyx : (z, y, x) array_like of bool
        The thin-slice reference; must hold tumour.
    case : str
        Case name copied into every row.
    spacing_mm : (3,) sequence of float
        Voxel spacing ``(dz, dy, dx)`` of the reference in mm.
    steps : sequence of int
        The ``k`` to evaluate.
    thickness_slices : float
        Emulated slab thickness in thin slices.
    phases : sequence of int, optional
        Phases of the kept slices; ``None`` = every phase ``0..k-1``.
    methods : sequence of str, optional
        Labels of :data:`METHODS` (and ``"ITK"``); default all of them.
    include_itk : bool
        Add ITK's interpolator when it is installed.
    end_caps : sequence of {"taper", "none"}
        End caps to run our methods with (ITK always ends flat).
    slab : {"centred", "flush"}
        Thick-slice emulation, see :func:`emulate_thick_labels`.
    extra : mapping, optional
        More methods: name -> ``f(thick, centres, n_thin) -> (z, y, x) bool``.

    Returns
    -------
    list of dict
        One row per step, phase, method and end cap: ``case``, ``k``,
        ``phase``, ``slab``, ``method``, ``end_caps``, ``n_kept`` (slices with tumour),
        ``dice``, ``hd95_mm``, ``volume_error_percent``.

    Raises
    ------
    InputError
        If the label is empty or invalid, or a parameter is out of range.
    ImportError
        If ``"ITK"`` is requested but not installed.
    """
    ref = as_mask(label_zyx, "label_zyx", 3)
    if not ref.any():
        raise InputError(f"label_zyx of case {case!r} holds no tumour voxel")
    if np.ndim(spacing_mm) != 1 or len(spacing_mm) != 3:
        raise InputError(f"spacing_mm must be (dz, dy, dx) in mm, got {spacing_mm!r}")
    names = _resolve_methods(methods, include_itk)
    n_ref = int(ref.sum())
    rows: list[dict[str, Any]] = []
    for k in steps:
        kk = _check_int(k, "step", 2)
        for ph in range(kk) if phases is None else phases:
            thick, centres = emulate_thick_labels(
                ref, step_slices=kk, thickness_slices=thickness_slices, phase=ph, slab=slab
            )
            runs: list[tuple[str, str, np.ndarray]] = []
            for name in names:
                caps = ("none",) if name == ITK_METHOD else tuple(end_caps)
                for cap in caps:
                    est = _reconstruct(
                        thick,
                        centres,
                        ref.shape[0],
                        name,
                        end_caps=cap,
                        pixel_spacing_mm=tuple(spacing_mm[1:]),
                    )
                    runs.append((name, cap, est))
            for name, fn in (extra or {}).items():
                runs.append((name, "-", as_mask(fn(thick, centres, ref.shape[0]), name, 3)))
            for name, cap, est in runs:
                rows.append(
                    {
                        "case": case,
                        "k": kk,
                        "phase": int(ph),
                        "slab": slab,
                        "method": name,
                        "end_caps": cap,
                        "n_kept": int(thick.reshape(len(thick), -1).any(axis=1).sum()),
                        "dice": _dice(est, ref),
                        "hd95_mm": _hd95_mm(est, ref, spacing_mm),
                        "volume_error_percent": 100.0 * (int(est.sum()) - n_ref) / n_ref,
                    }
                )
    return rows
