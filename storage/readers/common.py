"""Checks shared by every reader: modality, positive numbers, thickness/gap, volume, ids.

Also the one geometry rule of volume files (NIfTI, NRRD, MetaImage):
:func:`choose_slice_axis`.
"""

from __future__ import annotations

import math
import os
import re
import unicodedata
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from nibabel.orientations import aff2axcodes

from tumor3d.constants import (
    IN_PLANE_ORTHOGONALITY_TOL,
    MAX_VOXELS_DEFAULT,
    REL_TOL,
    SHEAR_TOL,
)
from tumor3d.errors import InputError
from tumor3d.imaging.affine import in_plane_shear, slice_plane_spacing_mm
from tumor3d.imaging.identity import MODALITIES, validate_patient_id
from tumor3d.imaging.orientation import canonical_orientation
from tumor3d.imaging.scan import Scan, SourceGrid
from tumor3d.validation import check_int, check_positive, non_finite_problem

__all__ = [
    "MAX_VOXELS_DEFAULT",
    "REL_TOL",
    "MAX_FIELD_OF_VIEW_MM",
    "MAX_STACK_EXTENT_MM",
    "MIN_VOXEL_MM",
    "check_field_of_view",
    "check_modality",
    "check_max_voxels",
    "check_voxel_count",
    "choose_slice_axis",
    "in_plane_axes",
    "derive_patient_id",
    "id_source_name",
    "scan_from_volume",
    "suggest_patient_id",
]

NIFTI_SUFFIXES = (".nii.gz", ".nii")
VOLUME_FILE_SUFFIXES = (*NIFTI_SUFFIXES, ".nrrd", ".nhdr", ".mha", ".mhd")
"""Suffixes stripped from a volume file's name to make its patient id."""
_UNSAFE_ID_CHARS = re.compile(r"[^A-Za-z0-9._-]")


#: The widest slice (mm) an MR scanner images: its bore is under 1 m across (clinical
#: bores 60-70 cm, fields of view up to about 50 cm). A volume whose slices span more
#: has a wrong voxel size in its header (cm or 10 x mm read as mm).
MAX_FIELD_OF_VIEW_MM = 1000.0
#: The longest stack (mm) across the slices: whole-body coverage is about 2 m.
MAX_STACK_EXTENT_MM = 2500.0
#: The finest voxel (mm) taken for MR: clinical and 7 T research scans stay above 0.1 mm.
#: Finer voxels mean a unit error (metres, or an sform scaled by 1e-3), and the
#: millimetre-sized structuring elements of skull removal would not fit in memory.
MIN_VOXEL_MM = 0.05


def check_field_of_view(
    shape_zyx: tuple[int, int, int],
    pixel_spacing_mm: tuple[float, float],
    slice_step_mm: float,
    where: str,
) -> None:
    """Refuse a volume larger, or voxels finer, than any MR scanner images: a wrong voxel size.

    Such a header (20 mm pixels for 2 mm, a unit error) would give volumes
    100-1000 times too large, and the brain surface's 2 mm grid over that
    extent asked for 205 GiB (measured by an audit).

    Raises
    ------
    InputError
        Naming the file, the extent and the likely cause.

    Examples
    --------
    >>> check_field_of_view((155, 240, 240), (1.0, 1.0), 1.0, "x.nii.gz")  # BraTS
    >>> check_field_of_view((4, 8, 8), (200.0, 200.0), 5.0, "x.nii.gz")
    Traceback (most recent call last):
    ...
    tumor3d.errors.InputError: x.nii.gz: the slices span 1600 x 1600 mm and the stack 20 mm: ...
    """
    nz, ny, nx = (int(n) for n in shape_zyx)
    dy, dx = (float(v) for v in pixel_spacing_mm)
    finest = min(dy, dx, float(slice_step_mm))
    if finest < MIN_VOXEL_MM:
        raise InputError(
            f"voxels of {dy:.3g} x {dx:.3g} mm and slices {float(slice_step_mm):.3g} mm apart: "
            f"finer than any MR scanner images (at least {MIN_VOXEL_MM:g} mm), so the voxel "
            "size in the header is wrong (a unit error?): fix the header's voxel size",
            where,
        )
    height, width, depth = ny * dy, nx * dx, nz * float(slice_step_mm)
    if max(height, width) > MAX_FIELD_OF_VIEW_MM or depth > MAX_STACK_EXTENT_MM:
        raise InputError(
            f"the slices span {height:.0f} x {width:.0f} mm and the stack {depth:.0f} mm: more "
            f"than any MR scanner images (slices under {MAX_FIELD_OF_VIEW_MM:.0f} mm across, "
            f"{MAX_STACK_EXTENT_MM:.0f} mm along the body), so the voxel size in the header is "
            "wrong (a unit error?): fix the header's voxel size",
            where,
        )


def id_source_name(path: str | os.PathLike[str]) -> str:
    """The input's file or folder name without its volume suffix: what an id is made from.

    >>> id_source_name("/data/pat 03.nii.gz")
    'pat 03'
    """
    name = Path(os.path.abspath(os.fspath(path))).name
    lower = name.lower()
    for suffix in VOLUME_FILE_SUFFIXES:
        if lower.endswith(suffix):
            return name[: -len(suffix)]
    return name


def derive_patient_id(path: str | os.PathLike[str]) -> str:
    """Make a folder-safe patient id from an input's file or folder name.

    A volume suffix (``.nii.gz``, ``.nii``, ``.nrrd``, ``.nhdr``, ``.mha``,
    ``.mhd``) is stripped from a file name; accented letters lose their accents
    (``ä`` -> ``a``: a user audit saw ``ärzt`` become ``rzt``); every other character
    outside ``[A-Za-z0-9._-]`` becomes ``_``; leading ``.``, ``_`` and ``-`` are
    dropped and the result is cut to 128 characters. It is then checked
    by :func:`tumor3d.imaging.scan.validate_patient_id`.

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
    >>> derive_patient_id("/data/ärzt_Müller.nii.gz")
    'arzt_Muller'
    """
    full_name = Path(os.path.abspath(os.fspath(path))).name
    name = id_source_name(path)
    plain = "".join(c for c in unicodedata.normalize("NFKD", name) if not unicodedata.combining(c))
    candidate = _UNSAFE_ID_CHARS.sub("_", plain).lstrip("._-")[:128]
    try:
        return validate_patient_id(candidate)
    except InputError as exc:
        raise InputError(
            f"cannot derive a patient id from the name {full_name!r} ({exc.problem}); "
            "pass patient_id explicitly",
            os.fspath(path),
        ) from None


def suggest_patient_id(path: str | os.PathLike[str]) -> str | None:
    """A patient id from the input's folder and file names, for an error's advice.

    ``pat3/flair.nii.gz`` -> ``pat3_flair``; None when none can be made.

    Examples
    --------
    >>> suggest_patient_id("/data/brats_pat0004/flair.nii.gz")
    'brats_pat0004_flair'
    """
    p = Path(os.path.abspath(os.fspath(path)))
    try:
        return derive_patient_id(p.with_name(f"{p.parent.name}_{p.name}"))
    except InputError:
        return None


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


def in_plane_axes(affine: np.ndarray, slice_axis: int) -> tuple[int, int]:
    """The two in-plane source axes of a grid as ``(x, y)``, the same for any storage order.

    ``x`` is the axis closer to left-right (then to anterior-posterior, then the
    lower axis), ``y`` the other: rows run front-back on an axial slice and
    top-bottom on a coronal or sagittal one, as the scans the learned method was
    trained on are stored. So a file storing the same slices transposed gives the
    same ``(z, y, x)`` array (the methods read a transposed slice otherwise: a
    BraTS FLAIR stored P-S-R lost 14.5 % of its learned volume). Only the order is
    chosen here; :func:`working_orientation` then sets the directions.

    Examples
    --------
    >>> in_plane_axes(np.diag([1.0, 1.0, 5.0, 1.0]), 2)
    (0, 1)
    >>> in_plane_axes(np.eye(4)[:, [1, 0, 2, 3]], 2)  # rows and columns stored swapped
    (1, 0)
    >>> in_plane_axes(np.eye(4)[:, [2, 1, 0, 3]], 2)  # sagittal: x along A, y along S
    (1, 0)
    """
    cols = np.asarray(affine, dtype=np.float64)[:3, :3]
    units = cols / np.linalg.norm(cols, axis=0)
    a, b = (k for k in range(3) if k != slice_axis)

    def rank(k: int) -> tuple[float, float]:  # rounded: a rounding error is no preference
        return round(abs(units[0, k]), 9), round(abs(units[1, k]), 9)

    return (b, a) if rank(b) > rank(a) else (a, b)


def scan_from_volume(
    data: np.ndarray,
    affine: np.ndarray,
    *,
    where: str,
    source: str,
    modality: str,
    patient_id: str,
    slice_thickness_mm: float | None,
    slice_gap_mm: float | None,
    file_thickness: Callable[[float], float | None] | None = None,
    orientation_stated: bool = True,
    xform_codes: tuple[int, int] = (1, 1),
    qform: np.ndarray | None = None,
) -> Scan:
    """Make a `Scan` from a 3-D volume in its file's voxel order and its RAS affine.

    The geometry rules of every volume file (NIfTI, NRRD, MetaImage): the
    slice axis is :func:`choose_slice_axis`; the voxel axes are permuted
    (never resampled) so that it becomes ``z``, the in-plane ones ordered by
    :func:`in_plane_axes`, and reversed into the working orientation
    (:func:`working_orientation`); the
    pixel spacings are the in-plane column lengths, which must be
    perpendicular; the slice step is the distance between slice planes
    (:func:`tumor3d.imaging.scan.slice_plane_spacing_mm`, less than the column
    length on a sheared grid).

    Parameters
    ----------
    data : ndarray, shape (i, j, k)
        Voxels in the file's axis order.
    affine : (4, 4) ndarray
        Voxel index ``(i, j, k, 1)`` -> RAS mm (finite, invertible).
    where : str
        The file, for error messages.
    source : str
        Start of ``Scan.source`` (e.g. ``"NIfTI file x.nii.gz"``).
    modality, patient_id : str
        Already validated.
    slice_thickness_mm, slice_gap_mm : float or None
        Validated overrides.
    file_thickness : callable, optional
        Given the slice step (mm), returns the thickness the file's metadata
        states, or None (and checks any stated spacing against the step).
    orientation_stated : bool
        False when the affine's directions are a reader's assumption
        (``Scan.orientation_stated``).
    xform_codes : tuple of int
        A NIfTI file's ``(sform_code, qform_code)``, which its outputs keep
        (``SourceGrid.xform_codes``).
    qform : (4, 4) ndarray, optional
        A NIfTI file's qform where it differs from ``affine`` (``SourceGrid.qform``).

    Returns
    -------
    Scan

    Raises
    ------
    InputError
        Perpendicularity violated, a constant or non-finite volume, or
        thickness/gap that contradict the geometry.
    """
    s = choose_slice_axis(affine)
    axes = (*in_plane_axes(affine, s), s)
    image = np.ascontiguousarray(data.transpose(axes[::-1]))  # (z, y, x)
    _check_volume(image, where)
    scan_affine = affine.copy()
    for k in range(3):
        scan_affine[:, k] = affine[:, axes[k]]
    shear = in_plane_shear(scan_affine)
    if shear > IN_PLANE_ORTHOGONALITY_TOL:
        angle = math.degrees(math.asin(max(0.0, min(1.0, 1.0 - shear))))
        raise InputError(
            f"the in-plane voxel axes {axes[0]} and {axes[1]} are not perpendicular "
            f"({angle:.2f} degrees apart): such an in-plane shear is not supported",
            where,
        )
    dx, dy = (float(np.linalg.norm(scan_affine[:3, k])) for k in (0, 1))
    column = float(np.linalg.norm(scan_affine[:3, 2]))
    step = slice_plane_spacing_mm(scan_affine)
    stated = None if file_thickness is None else file_thickness(step)
    thickness, gap = _resolve_thickness(step, stated, slice_thickness_mm, slice_gap_mm, where)
    text = f"{source}, {image.shape[0]} slices along voxel axis {s}"
    if column - step > SHEAR_TOL * column:
        text += (
            f" (sheared grid: slice planes {step:.4g} mm apart, slice-axis column {column:.4g} mm)"
        )
    scan = Scan(
        image=image,
        affine=scan_affine,
        pixel_spacing_mm=(dy, dx),
        slice_step_mm=step,
        slice_thickness_mm=thickness,
        slice_gap_mm=gap,
        modality=modality,
        patient_id=patient_id,
        source=text,
        source_grid=SourceGrid(
            shape=tuple(data.shape),
            affine=affine,
            axes=axes,
            xform_codes=xform_codes,
            qform=qform,
        ),  # fmt: skip
        orientation_stated=orientation_stated,
    )
    return working_orientation(scan)


def working_orientation(scan: Scan) -> Scan:
    """A read scan in the working orientation, its source naming the stored one.

    :func:`tumor3d.imaging.scan.canonical_orientation`, whose axis reversals
    the source grid records; ``Scan.source`` then ends with, for example,
    ``"stored LAS, read as LPS"`` (nibabel's axis codes of the Scan's axes).
    """
    out = canonical_orientation(scan)
    if out is scan:
        return scan
    stored, working = ("".join(aff2axcodes(a)) for a in (scan.affine, out.affine))
    return replace(out, source=f"{scan.source}, stored {stored}, read as {working}")


def check_max_voxels(max_voxels: int) -> int:
    """Validate the ``max_voxels`` option (an integer >= 1)."""
    return check_int(max_voxels, "max_voxels", minimum=1)


def check_voxel_count(shape: tuple[int, ...], max_voxels: int, where: str) -> None:
    """Refuse a volume whose declared shape exceeds ``max_voxels``, before reading it.

    Raises
    ------
    InputError
        Naming the declared shape, its voxel count, the limit and the option.
    """
    n = math.prod(int(s) for s in shape)
    if n > max_voxels:
        dims = " x ".join(str(int(s)) for s in shape)
        raise InputError(
            f"the header declares {dims} = {n:,} voxels, more than the limit of "
            f"{max_voxels:,} (option max_voxels, CLI --max-voxels; raise it only for a "
            "genuine volume)",
            where,
        )


def check_modality(modality: Any, where: str | None = None) -> str:
    """The modality in lower case (``"FLAIR"`` -> ``"flair"``), or an error naming the choices.

    >>> check_modality(" T1c ")
    't1c'
    """
    value = modality.strip().lower() if isinstance(modality, str) else None
    if value not in MODALITIES:
        raise InputError(
            f"unknown modality {modality!r}: expected one of {', '.join(MODALITIES)}", where
        )
    return value


def _check_override(name: str, value: float | None, *, allow_zero: bool) -> float | None:
    """A thickness or gap given by hand (an option, an API argument): a number of mm.

    :class:`InputError` naming it otherwise, also for text (``'5'`` is the user's input,
    not a programming error).
    """
    if value is None:
        return None
    try:
        return _positive_number(value, name, None, allow_zero=allow_zero)
    except TypeError as exc:
        raise InputError(str(exc)) from None


def _positive_number(
    value: Any, name: str, where: str | None, *, allow_zero: bool = False
) -> float:
    """A positive (or non-negative) number of mm; see :func:`tumor3d.validation.check_positive`."""
    return check_positive(value, name, allow_zero=allow_zero, unit="mm", where=where)


#: The thickest slice, in slice steps, that a thickness given by hand may state: a slab as
#: thick as two steps already lies half in each neighbour (the usual overlapping
#: reconstruction); typed beyond it, a typo (or cm read as mm).
MAX_OVERLAP_STEPS = 2.0


def _resolve_thickness(
    step: float,
    file_thickness: float | None,
    thickness_override: float | None,
    gap_override: float | None,
    where: str,
) -> tuple[float, float]:
    """Combine the geometric step with stated thickness/gap (see the module docstring).

    Whatever states the thickness (the option, or the file's metadata): at most the
    step, the rest of the step is the gap; above it, the slices overlap (a negative gap,
    said in the run's notes: :func:`tumor3d.imaging.affine.slice_overlap_note`). The
    file's value is read as it states (no volume depends on it: Eq. 7's slab height is
    the step in every case); one given by hand more than :data:`MAX_OVERLAP_STEPS` steps
    thick is a typo, an error.

    >>> _resolve_thickness(5.0, None, 2.0, None, "x")
    (2.0, 3.0)
    >>> _resolve_thickness(5.0, 6.0, None, None, "x")
    (6.0, -1.0)
    """
    thickness = thickness_override if thickness_override is not None else file_thickness
    if (
        gap_override is None
        and thickness_override is not None
        and thickness_override > MAX_OVERLAP_STEPS * step * (1 + REL_TOL)
    ):
        raise InputError(
            f"slice_thickness_mm = {thickness:g} mm is larger than the slice step {step:.6g} mm "
            f"of the image geometry by more than the step (overlapping slices are at most "
            f"{MAX_OVERLAP_STEPS:g} steps thick): give the acquired thickness",
            where,
        )
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
    problem = non_finite_problem(image)
    if problem:
        raise InputError(problem, where)
    lo, hi = float(image.min()), float(image.max())
    if lo == hi:
        what = "all-zero" if lo == 0 else f"constant (every voxel = {lo:g})"
        raise InputError(f"the volume is {what}: there is nothing to segment", where)


def _describe(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[0]}" if text else type(exc).__name__
