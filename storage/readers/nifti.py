"""NIfTI reader: a ``.nii``/``.nii.gz`` file (and its BIDS JSON sidecar) -> `Scan`."""

from __future__ import annotations

import json
import logging
import os
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path
from typing import Any

import numpy as np
from nibabel.orientations import aff2axcodes

from tumor3d.constants import SINGULAR_DET_TOL
from tumor3d.errors import InputError
from tumor3d.imaging.identity import validate_patient_id
from tumor3d.imaging.scan import Scan
from tumor3d.segmentation.review import ORIENTATION_UNSTATED
from tumor3d.storage.nifti import differing_qform, placed_affine, xform_codes
from tumor3d.storage.readers.common import (
    MAX_VOXELS_DEFAULT,
    NIFTI_SUFFIXES,
    REL_TOL,
    _check_override,
    _describe,
    _positive_number,
    check_max_voxels,
    check_modality,
    check_voxel_count,
    derive_patient_id,
    scan_from_volume,
)
from tumor3d.storage.readers.options import ReadOptions
from tumor3d.storage.readers.registry import register_reader

__all__ = [
    "ORIENTATION_UNSTATED",
    "load_nifti_volume",
    "nibabel_header_notes",
    "quiet_nibabel",
    "read_nifti_scan",
]

#: nibabel's logger of the header repairs it makes on reading (``nibabel.imageglobals``).
_NIBABEL_LOGGER = "nibabel.global"
_collected: ContextVar[list[str] | None] = ContextVar("nibabel_header_notes", default=None)
#: Axis codes of the inputs read in the collecting block whose header states no orientation.
_unstated: ContextVar[list[str] | None] = ContextVar("nifti_orientation_unstated", default=None)


class _NibabelCollector(logging.Handler):
    """nibabel's messages into the collecting reader's list (else dropped), never printed."""

    def emit(self, record: logging.LogRecord) -> None:
        found = _collected.get()
        if found is None:
            return
        try:
            text = " ".join(record.getMessage().split())
        except Exception:  # a malformed record: nothing to say
            return
        if text and text not in found:
            found.append(text)


def quiet_nibabel() -> None:
    """Route nibabel's header messages to :func:`nibabel_header_notes`, never to the console.

    nibabel logs each repair it makes to a header on reading (an invalid
    ``qform_code``, a ``sizeof_hdr`` other than 348) on its own logger, whose
    handler printed it to stderr, once per reading, and again through
    Prefect's console handler. Idempotent; call it after importing nibabel
    (its import adds the printing handler).
    """
    logger = logging.getLogger(_NIBABEL_LOGGER)
    # Enforced on every call, not once: a later logging set-up (Prefect's,
    # a notebook's ``logging.basicConfig``/``dictConfig``, a test harness)
    # can re-enable propagation or add a printing handler after the first.
    ours = [h for h in logger.handlers if isinstance(h, _NibabelCollector)]
    for handler in list(logger.handlers):
        if handler not in ours[:1]:
            logger.removeHandler(handler)
    if not ours:
        logger.addHandler(_NibabelCollector())
    logger.propagate = False
    logger.disabled = False


@contextmanager
def nibabel_header_notes(name: str) -> Iterator[list[str]]:
    """Collect, as one-line notes naming the file, nibabel's header repairs within the block.

    Only in this context (this thread); elsewhere they are dropped: the
    ingest-scan stage reads the input and reports them, the other readings of
    the same file (the command line's checks) stay quiet.
    """
    import nibabel  # noqa: F401  (its import installs the handler quiet_nibabel removes)

    quiet_nibabel()
    found: list[str] = []
    unstated: list[str] = []
    notes: list[str] = []
    token = _collected.set(found)
    token_unstated = _unstated.set(unstated)
    try:
        yield notes
    finally:
        _collected.reset(token)
        _unstated.reset(token_unstated)
        if found:
            notes.append(
                f"{name}: nibabel repaired the NIfTI header on reading: {'; '.join(found)}"
            )
        for codes in unstated[:1]:
            notes.append(
                f"{name}: {ORIENTATION_UNSTATED}: read with nibabel's default axes ({codes}), "
                "so left-right and front-back are unverified, and the segmentation and its "
                "volume with them (the learned model reads a head as it lies: this guess "
                "may turn it); check them, or give the file "
                "its orientation (the masks on its grid state none either and overlay it in "
                "any viewer; the meshes and the interpolated mask are placed by that guess, "
                "which 3D Slicer and ITK-SNAP do not share)"
            )


def read_nifti_scan(
    path: str | os.PathLike[str],
    *,
    modality: str = "t2",
    patient_id: str | None = None,
    slice_thickness_mm: float | None = None,
    slice_gap_mm: float | None = None,
    max_voxels: int = MAX_VOXELS_DEFAULT,
) -> Scan:
    """Read a 3-D NIfTI file (or 4-D with one volume) as a `Scan`.

    The affine is nibabel's ``img.affine`` (sform or qform as nibabel
    chooses); the slice axis follows :func:`choose_slice_axis`. An optional
    BIDS JSON sidecar (``x.nii.gz`` -> ``x.json``) gives ``SliceThickness``
    and ``SpacingBetweenSlices`` (centre to centre; must match the affine's
    slice step within 1 %).

    Parameters
    ----------
    path : str or path-like
        The ``.nii`` or ``.nii.gz`` file.
    modality, patient_id, slice_thickness_mm, slice_gap_mm, max_voxels
        As for :func:`read_scan`.

    Returns
    -------
    Scan

    Raises
    ------
    InputError
        Unreadable file, more voxels declared than ``max_voxels`` (checked
        on the header, before any voxel is read), unsupported dimensionality, a single 2-D image,
        a singular affine, a constant or non-finite volume, or a sidecar that
        contradicts the image.
    """
    p = Path(path)
    where = str(p)
    mod = check_modality(modality)
    pid = derive_patient_id(p) if patient_id is None else validate_patient_id(patient_id)
    thickness_override = _check_override("slice_thickness_mm", slice_thickness_mm, allow_zero=False)
    gap_override = _check_override("slice_gap_mm", slice_gap_mm, allow_zero=True)
    limit = check_max_voxels(max_voxels)
    if not p.is_file():
        raise InputError("no such file", where)
    data, affine, codes, qform = _load_nifti(p, limit)
    stated = any(codes)
    unstated = _unstated.get()
    if not stated and unstated is not None:  # the run's note (nibabel_header_notes)
        unstated.append("".join(aff2axcodes(affine)))

    return scan_from_volume(
        data,
        affine,
        where=where,
        source=f"NIfTI file {p.name}",
        modality=mod,
        patient_id=pid,
        slice_thickness_mm=thickness_override,
        slice_gap_mm=gap_override,
        file_thickness=lambda step: _read_bids_sidecar(p, step),
        orientation_stated=stated,
        xform_codes=codes,
        qform=qform,
    )


def load_nifti_volume(p: Path, limit: int) -> tuple[np.ndarray, np.ndarray]:
    """The 3-D voxel values and affine of a NIfTI file, without an intensity check.

    What :func:`read_nifti_scan` checks before it builds the Scan (and what a
    given brain mask is checked for, where a constant volume is fine): a
    NIfTI image, at most ``limit`` voxels by the header (before any voxel is
    read), 3-D (or 4-D with one volume) with at least 2 slices, a regular
    finite affine, readable voxel data.

    Returns
    -------
    data : ndarray of float32, 3-D
        Voxel values in the file's own index order.
    affine : (4, 4) ndarray
        Voxel index ``(i, j, k, 1)`` -> RAS mm (:func:`tumor3d.storage.nifti.placed_affine`).

    Raises
    ------
    InputError
        Naming the file and the problem.
    """
    return _load_nifti(p, limit)[:2]


def _load_nifti(
    p: Path, limit: int
) -> tuple[np.ndarray, np.ndarray, tuple[int, int], np.ndarray | None]:
    """:func:`load_nifti_volume`, the header's form codes and its differing qform.

    The codes are ``(sform_code, qform_code)``; the qform is returned where it differs
    from the affine read (:func:`tumor3d.storage.nifti.differing_qform`). The
    orientation is stated by a code above 0; without either, the affine is nibabel's
    default axes (LAS), a guess (:func:`tumor3d.storage.nifti.placed_affine`).
    """
    import nibabel as nib

    quiet_nibabel()
    where = str(p)
    try:
        img = nib.load(where)
    except Exception as exc:  # nibabel raises many types for a bad file
        raise InputError(f"not a readable NIfTI image ({_describe(exc)})", where) from exc
    if not isinstance(img, nib.Nifti1Image | nib.Nifti2Image):
        raise InputError(f"not a NIfTI image (nibabel read it as {type(img).__name__})", where)

    shape = tuple(int(s) for s in img.shape)
    check_voxel_count(shape, limit, where)
    if len(shape) == 4 and shape[3] == 1:
        shape = shape[:3]
    elif len(shape) == 4:
        raise InputError(
            f"a 4-D image with {shape[3]} volumes (shape {shape}): give a single 3-D volume",
            where,
        )
    elif len(shape) > 4:
        raise InputError(f"a {len(shape)}-D image (shape {shape}): give a 3-D volume", where)
    if len(shape) < 3 or min(shape) < 2:
        raise InputError(f"a single 2-D image (shape {shape}): at least 2 slices are needed", where)

    dtype = img.get_data_dtype()
    if dtype.fields is not None:  # RGB, RGBA: several values per voxel
        raise InputError(
            f"{len(dtype.fields)} values per voxel (data type {dtype}, e.g. RGB): give a "
            "single-channel gray-level image",
            where,
        )
    if dtype.kind == "c":  # the imaginary part would be dropped without a word
        raise InputError(
            f"complex voxel values (data type {dtype}): give the magnitude image", where
        )
    _check_voxel_size(p, img)
    # in mm first: a 0.1 mm grid written in metres has a determinant of 1e-12
    affine = placed_affine(img)
    if not np.all(np.isfinite(affine)) or abs(np.linalg.det(affine[:3, :3])) < SINGULAR_DET_TOL:
        raise InputError("the image affine is singular or not finite", where)
    codes = xform_codes(img.header)
    try:
        data = np.asarray(img.get_fdata(dtype=np.float32), dtype=np.float32)
    except Exception as exc:
        raise InputError(f"cannot read the voxel data ({_describe(exc)})", where) from exc
    return data.reshape(shape), affine, codes, differing_qform(img, affine)


def _check_voxel_size(p: Path, img: Any) -> None:
    """Refuse a zero voxel size that nibabel would silently read as 1 mm.

    Without an sform, the affine's lengths are the header's ``pixdim``; nibabel
    replaces a zero there by 1 when it loads the header, which gave a 5 mm
    slice step as 1 mm (a volume five times too small). The header is read
    again unchecked to see what the file says.
    """
    from nibabel.openers import ImageOpener

    try:
        with ImageOpener(str(p)) as f:
            raw = type(img.header).from_fileobj(f, check=False)
        sform_code = int(raw["sform_code"])
        pixdim = np.asarray(raw["pixdim"][1:4], dtype=np.float64)
    except Exception:  # the header was read once already: leave it to that reading
        return
    if sform_code == 0 and np.any(pixdim == 0):
        raise InputError(
            f"the header gives a voxel size of 0 (pixdim {' x '.join(f'{v:g}' for v in pixdim)}) "
            "and no sform: the voxel size is unknown; fix the header (pixdim) or give a "
            "file with its voxel size",
            str(p),
        )


def _bids_sidecar_path(p: Path) -> Path:
    lower = p.name.lower()
    for suffix in NIFTI_SUFFIXES:
        if lower.endswith(suffix):
            return p.with_name(p.name[: -len(suffix)] + ".json")
    return p.with_suffix(".json")


def _read_bids_sidecar(p: Path, step: float) -> float | None:
    """Return the sidecar's SliceThickness (or None); check SpacingBetweenSlices."""
    sidecar = _bids_sidecar_path(p)
    if not sidecar.is_file():
        return None
    try:
        meta = json.loads(sidecar.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"not a readable JSON sidecar ({_describe(exc)})", str(sidecar)) from exc
    if not isinstance(meta, dict):
        raise InputError("the JSON sidecar must hold an object", str(sidecar))
    thickness = None
    if "SliceThickness" in meta:
        thickness = _positive_number(meta["SliceThickness"], "SliceThickness", str(sidecar))
    if "SpacingBetweenSlices" in meta:
        spacing = _positive_number(
            meta["SpacingBetweenSlices"], "SpacingBetweenSlices", str(sidecar)
        )
        if abs(spacing - step) > REL_TOL * step:
            raise InputError(
                f"SpacingBetweenSlices = {spacing:g} mm disagrees with the slice step "
                f"{step:.6g} mm of the image affine (more than 1 %)",
                str(sidecar),
            )
    return thickness


@register_reader("nifti", accepts="a NIfTI file (.nii, .nii.gz)", suffixes=NIFTI_SUFFIXES)
def _read_nifti(path: Path, options: ReadOptions) -> Scan:
    return read_nifti_scan(path, modality=options.modality or "t2", **options.common())
