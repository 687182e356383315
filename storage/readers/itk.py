"""NRRD and MetaImage reader (``.nrrd``, ``.nhdr``, ``.mha``, ``.mhd``) -> `Scan`, via SimpleITK.

SimpleITK (the maintained ITK wrapping) reads the header first, so the
declared size is checked against ``max_voxels`` before any voxel is read.

Geometry
--------
ITK maps the voxel index ``(i, j, k)`` (``i`` fastest) to **LPS** millimetres,

    p_LPS = origin + D @ diag(spacing) @ (i, j, k)

with ``D`` the direction matrix (its columns are the axis directions). The
RAS affine is ``diag(-1, -1, 1, 1) @ [[D diag(spacing), origin], [0, 1]]``:
the first two rows negated, exactly as for DICOM. ``GetArrayFromImage``
returns the voxels as ``(k, j, i)``; they are transposed to the file's own
order ``(i, j, k)`` and then follow the same rules as a NIfTI volume
(:func:`tumor3d.storage.readers.common.scan_from_volume`: the slice axis by
:func:`tumor3d.storage.readers.common.choose_slice_axis`, axes permuted and reversed
into the working orientation, never resampled, the slice step the distance between
slice planes).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from tumor3d.constants import SINGULAR_DET_TOL
from tumor3d.errors import InputError
from tumor3d.imaging.identity import validate_patient_id
from tumor3d.imaging.scan import Scan
from tumor3d.storage.inputs import detached_data_files
from tumor3d.storage.readers.common import (
    MAX_VOXELS_DEFAULT,
    _check_override,
    _describe,
    check_max_voxels,
    check_modality,
    check_voxel_count,
    derive_patient_id,
    scan_from_volume,
)
from tumor3d.storage.readers.options import ReadOptions
from tumor3d.storage.readers.registry import register_reader

__all__ = ["ITK_SUFFIXES", "itk_ras_affine", "read_itk_scan"]

ITK_SUFFIXES = (".nrrd", ".nhdr", ".mha", ".mhd")
"""File suffixes (lower case) read by :func:`read_itk_scan`."""

LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])
"""Flips the first two world axes: LPS <-> RAS (its own inverse)."""


def itk_ras_affine(
    spacing: tuple[float, ...], origin: tuple[float, ...], direction: tuple[float, ...]
) -> np.ndarray:
    """The RAS affine of an ITK image's geometry.

    Parameters
    ----------
    spacing : 3 floats
        Voxel spacing along ``i, j, k`` in mm.
    origin : 3 floats
        LPS position of voxel ``(0, 0, 0)`` in mm.
    direction : 9 floats
        The 3x3 direction matrix, row-major (ITK's ``GetDirection()``);
        column ``a`` is the LPS direction of voxel axis ``a``.

    Returns
    -------
    (4, 4) ndarray
        Voxel index ``(i, j, k, 1)`` -> RAS mm.

    Examples
    --------
    >>> a = itk_ras_affine((1.0, 2.0, 5.0), (10.0, 20.0, 30.0), (1, 0, 0, 0, 1, 0, 0, 0, 1))
    >>> np.diag(a).tolist(), a[:3, 3].tolist()
    ([-1.0, -2.0, 5.0, 1.0], [-10.0, -20.0, 30.0])
    """
    lps = np.eye(4)
    lps[:3, :3] = np.asarray(direction, dtype=np.float64).reshape(3, 3) * np.asarray(
        spacing, dtype=np.float64
    )
    lps[:3, 3] = np.asarray(origin, dtype=np.float64)
    return LPS_TO_RAS @ lps


def read_itk_scan(
    path: str | os.PathLike[str],
    *,
    modality: str = "t2",
    patient_id: str | None = None,
    slice_thickness_mm: float | None = None,
    slice_gap_mm: float | None = None,
    max_voxels: int = MAX_VOXELS_DEFAULT,
) -> Scan:
    """Read a 3-D NRRD or MetaImage file as a `Scan` (see the module docstring).

    Parameters
    ----------
    path : str or path-like
        A ``.nrrd``, ``.nhdr``, ``.mha`` or ``.mhd`` file (a detached header
        finds its data file as the format says).
    modality, patient_id, slice_thickness_mm, slice_gap_mm, max_voxels
        As for :func:`tumor3d.storage.readers.read_scan`. These formats state no
        slice thickness, so it equals the step unless given.

    Returns
    -------
    Scan

    Raises
    ------
    InputError
        Unreadable file, more voxels declared than ``max_voxels``, not a
        single-component 3-D image (a 4-D image with one volume is
        accepted), a single 2-D image, a singular geometry, a constant or
        non-finite volume, a detached header naming a data file outside its
        folder (``ElementDataFile = ../../etc/passwd``).
    """
    import SimpleITK as sitk

    p = Path(path)
    where = str(p)
    mod = check_modality(modality)
    pid = derive_patient_id(p) if patient_id is None else validate_patient_id(patient_id)
    thickness_override = _check_override("slice_thickness_mm", slice_thickness_mm, allow_zero=False)
    gap_override = _check_override("slice_gap_mm", slice_gap_mm, allow_zero=True)
    limit = check_max_voxels(max_voxels)
    if not p.is_file():
        raise InputError("no such file", where)
    detached_data_files(p)  # a header naming data outside its folder is refused, never read
    kind = "NRRD" if p.name.lower().endswith((".nrrd", ".nhdr")) else "MetaImage"
    # ITK prints warnings for odd headers to stderr; the reader reports in one line instead
    shown = sitk.ProcessObject.GetGlobalWarningDisplay()
    sitk.ProcessObject.SetGlobalWarningDisplay(False)
    try:
        data, affine = _read_itk(sitk, where, kind, limit)
    finally:
        sitk.ProcessObject.SetGlobalWarningDisplay(shown)
    return scan_from_volume(
        np.ascontiguousarray(data),
        affine,
        where=where,
        source=f"{kind} file {p.name}",
        modality=mod,
        patient_id=pid,
        slice_thickness_mm=thickness_override,
        slice_gap_mm=gap_override,
    )


def _read_itk(sitk: Any, where: str, kind: str, limit: int) -> tuple[np.ndarray, np.ndarray]:
    """Header check, then voxels ``(i, j, k)`` float32 and the RAS affine."""
    reader = sitk.ImageFileReader()
    reader.SetFileName(where)
    try:
        reader.ReadImageInformation()
    except RuntimeError as exc:
        raise InputError(f"not a readable {kind} image ({_itk_message(exc)})", where) from None
    size = tuple(int(s) for s in reader.GetSize())
    check_voxel_count(size, limit, where)
    if reader.GetNumberOfComponents() != 1:
        raise InputError(
            f"a {reader.GetNumberOfComponents()}-component (vector or colour) image: give a "
            "scalar volume",
            where,
        )
    if len(size) == 4 and size[3] == 1:
        size = size[:3]
    elif len(size) != 3:
        raise InputError(f"a {len(size)}-D image (size {size}): give a 3-D volume", where)
    if min(size) < 2:
        raise InputError(f"a single 2-D image (size {size}): at least 2 slices are needed", where)
    try:
        image = reader.Execute()
        if image.GetDimension() == 4:
            image = image[:, :, :, 0]
        data = sitk.GetArrayFromImage(image).astype(np.float32).transpose(2, 1, 0)  # (i, j, k)
    except RuntimeError as exc:
        raise InputError(f"cannot read the voxel data ({_itk_message(exc)})", where) from None
    except MemoryError as exc:
        raise InputError(f"not enough memory for the voxel data ({_describe(exc)})", where) from exc
    affine = itk_ras_affine(image.GetSpacing(), image.GetOrigin(), image.GetDirection())
    if not np.all(np.isfinite(affine)) or abs(np.linalg.det(affine[:3, :3])) < SINGULAR_DET_TOL:
        raise InputError("the image geometry (spacing, direction) is singular or not finite", where)
    return data, affine


def _itk_message(exc: BaseException) -> str:
    """The useful last line of an ITK exception (they span many lines)."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    for ln in reversed(lines):
        if ln.lower().startswith(("description:", "itk::error")):
            return ln.split(":", 1)[1].strip()[:200]
    return (lines[-1] if lines else type(exc).__name__)[:200]


@register_reader(
    "itk", accepts="an NRRD or MetaImage file (.nrrd, .nhdr, .mha, .mhd)", suffixes=ITK_SUFFIXES
)
def _read_itk_file(path: Path, options: ReadOptions) -> Scan:
    return read_itk_scan(path, modality=options.modality or "t2", **options.common())
