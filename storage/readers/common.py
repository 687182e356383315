"""Checks shared by every reader: modality, positive numbers, thickness/gap, volume, ids.

Also the one geometry rule of volume files (NIfTI, NRRD, MetaImage):
:func:`choose_slice_axis`.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from tumor3d.constants import REL_TOL
from tumor3d.errors import InputError
from tumor3d.scan import MODALITIES, validate_patient_id
from tumor3d.validation import check_positive

__all__ = [
    "REL_TOL",
    "choose_slice_axis",
    "derive_patient_id",
]

NIFTI_SUFFIXES = (".nii.gz", ".nii")
_UNSAFE_ID_CHARS = re.compile(r"[^A-Za-z0-9._-]")


def derive_patient_id(path: str | os.PathLike[str]) -> str:
    """Make a folder-safe patient id from an input's file or folder name.

    ``.nii.gz``/``.nii`` is stripped from a file name; every character
    outside ``[A-Za-z0-9._-]`` becomes ``_``; leading ``.``, ``_`` and ``-``
    are dropped and the result is cut to 128 characters. It is then checked
    by :func:`tumor3d.scan.validate_patient_id`.

    Parameters
    ----------
    path : str or path-like
        The input file or folder (it need not exist).

    Returns
    -------
    str
        The id.

    Raises
    ------
    InputError
        If no valid id remains (e.g. the name is only punctuation).

    Examples
    --------
    >>> derive_patient_id("/data/pat 03.nii.gz")
    'pat_03'
    """
    full_name = Path(os.path.abspath(os.fspath(path))).name
    name = full_name
    lower = name.lower()
    for suffix in NIFTI_SUFFIXES:
        if lower.endswith(suffix):
            name = name[: -len(suffix)]
            break
    candidate = _UNSAFE_ID_CHARS.sub("_", name).lstrip("._-")[:128]
    try:
        return validate_patient_id(candidate)
    except InputError as exc:
        raise InputError(
            f"cannot derive a patient id from the name {full_name!r} ({exc.problem}); "
            "pass patient_id explicitly",
            os.fspath(path),
        ) from None


def choose_slice_axis(affine: np.ndarray) -> int:
    """Pick the slice (acquisition) axis of a voxel grid from its affine.

    The axis with the coarsest spacing (affine column norm) wins; axes within
    1 % of it tie, and the tie goes to the axis whose unit column has the
    largest ``|S|`` (superior-inferior) component, then to the highest axis.

    Parameters
    ----------
    affine : (4, 4) array_like
        Voxel index (source order) -> RAS mm.

    Returns
    -------
    int
        The source voxel axis (0, 1 or 2) that is the slice axis.

    Examples
    --------
    >>> choose_slice_axis(np.diag([1.0, 1.0, 1.0, 1.0]))
    2
    >>> choose_slice_axis(np.diag([0.9, 5.0, 0.9, 1.0]))
    1
    """
    cols = np.asarray(affine, dtype=np.float64)[:3, :3]
    spacing = np.linalg.norm(cols, axis=0)
    coarsest = float(spacing.max())
    candidates = [a for a in range(3) if coarsest < spacing[a] * (1.0 + REL_TOL)]
    best = candidates[0]
    best_si = -1.0
    for a in candidates:
        si = abs(cols[2, a]) / spacing[a]
        if si >= best_si:  # ">=" so that an exact tie goes to the higher axis
            best, best_si = a, si
    return int(best)


def _check_modality(modality: Any, where: str | None = None) -> str:
    value = modality.strip().lower() if isinstance(modality, str) else None
    if value not in MODALITIES:
        raise InputError(
            f"unknown modality {modality!r}: expected one of {', '.join(MODALITIES)}", where
        )
    return value


def _check_override(name: str, value: float | None, *, allow_zero: bool) -> float | None:
    if value is None:
        return None
    return _positive_number(value, name, None, allow_zero=allow_zero)


def _positive_number(
    value: Any, name: str, where: str | None, *, allow_zero: bool = False
) -> float:
    """A positive (or non-negative) number of mm; see :func:`tumor3d.validation.check_positive`."""
    return check_positive(value, name, allow_zero=allow_zero, unit="mm", where=where)


def _resolve_thickness(
    step: float,
    file_thickness: float | None,
    thickness_override: float | None,
    gap_override: float | None,
    where: str,
) -> tuple[float, float]:
    """Combine the geometric step with stated thickness/gap (see the module docstring)."""
    thickness = thickness_override if thickness_override is not None else file_thickness
    if gap_override is None:
        if thickness is None:
            thickness = step
        return thickness, step - thickness
    if thickness is None:
        thickness = step - gap_override
        if thickness <= 0:
            raise InputError(
                f"slice_gap_mm = {gap_override:g} mm is not smaller than the slice step "
                f"{step:.6g} mm of the image geometry",
                where,
            )
    elif abs(thickness + gap_override - step) > REL_TOL * step:
        raise InputError(
            f"slice thickness {thickness:g} mm + gap {gap_override:g} mm = "
            f"{thickness + gap_override:g} mm disagrees with the slice step {step:.6g} mm of "
            "the image geometry (more than 1 %)",
            where,
        )
    return thickness, gap_override


def _check_volume(image: np.ndarray, where: str) -> None:
    finite = np.isfinite(image)
    n_bad = int(image.size - np.count_nonzero(finite))
    if n_bad:
        n_nan = int(np.count_nonzero(np.isnan(image)))
        raise InputError(
            f"{n_bad} of {image.size} voxel values are not finite ({n_nan} NaN, "
            f"{n_bad - n_nan} infinite)",
            where,
        )
    lo, hi = float(image.min()), float(image.max())
    if lo == hi:
        what = "all-zero" if lo == 0 else f"constant (every voxel = {lo:g})"
        raise InputError(f"the volume is {what}: there is nothing to segment", where)


def _describe(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__
