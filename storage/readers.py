"""Input readers: a NIfTI file, a DICOM series or a stack of 2-D images -> `Scan`.

:func:`read_scan` is the one entry point. It dispatches on what ``path`` is:

* a ``.nii`` / ``.nii.gz`` file -> :func:`read_nifti_scan`;
* a folder holding a ``stack.yaml`` (or ``slices.yaml``) sidecar ->
  :func:`read_image_stack` (2-D PNG/TIFF/JPEG slices);
* any other folder -> :func:`read_dicom_series` (one DICOM series).

Every reader returns a :class:`tumor3d.scan.Scan`: a float32 ``(z, y, x)``
image with ``z`` the slice axis, an affine mapping the voxel index
``(x, y, z, 1)`` to RAS mm, and a :class:`tumor3d.scan.SourceGrid` that
writes Scan-grid arrays back in the input's own voxel grid.

Slice axis of a NIfTI volume (the one rule)
-------------------------------------------
The voxel spacings are the norms of the affine's first three columns. The
voxel axis with the **coarsest spacing** is the slice axis. When several axes
are within 1 % of the coarsest spacing (e.g. an isotropic 1 mm volume), the
one among them whose direction is **closest to superior-inferior** (largest
``|S|`` component of its unit affine column) is chosen, i.e. axial; an exact
tie goes to the highest voxel axis. The voxel axes are only permuted (never
resampled, never flipped) so that the slice axis becomes ``z``; the two other
axes keep their source order as ``(x, y)``. See :func:`choose_slice_axis`.

Slice thickness and gap
-----------------------
``slice_step_mm`` (centre to centre) always comes from the geometry (the
affine, the DICOM positions, or thickness + gap for an image stack). The
nominal thickness comes from, in this order: the ``slice_thickness_mm``
argument; the file (the BIDS JSON sidecar's ``SliceThickness`` beside a NIfTI
file, ``x.nii.gz`` -> ``x.json``; DICOM ``SliceThickness``; the stack
sidecar); else it equals the step. The gap is ``step - thickness`` unless
``slice_gap_mm`` is given, in which case thickness + gap must equal the step
within 1 % (an ``InputError`` otherwise); if the thickness is not known at
all it is then ``step - gap``.

DICOM geometry
--------------
Slices are sorted by ``ImagePositionPatient`` projected on the slice normal
``n = r x c`` (``r = IOP[0:3]``, the direction of increasing column index;
``c = IOP[3:6]``, of increasing row index), never by file name or
``InstanceNumber``. The affine, in LPS, has columns ``r * PixelSpacing[1]``
(x = column index), ``c * PixelSpacing[0]`` (y = row index), ``n * step``
(z = sorted slice index) and origin the first sorted slice's position; its
first two rows are negated to give RAS (DICOM PS3.3 C.7.6.2.1.1).

Image stack convention
----------------------
2-D slices carry no patient geometry, so a display convention is used:
increasing column index points to the patient's left, increasing row index
to posterior and increasing slice index (the sidecar's ``order``, or the
natural sort of the file names) to superior, i.e. the affine is
``diag(-dx, -dy, step, 1)`` with ``step = thickness + gap`` and origin 0.

Protected health information
----------------------------
Patient ids come from the caller or from the file/folder name, never from
DICOM ``PatientName``/``PatientID``; ``Scan.source`` holds only the reader
kind, the file or folder name and the number of slices.
"""

from __future__ import annotations

import json
import math
import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from tumor3d.errors import InputError
from tumor3d.scan import MODALITIES, Scan, SourceGrid, validate_patient_id

__all__ = [
    "IMAGE_STACK_SUFFIXES",
    "MODALITIES",
    "REL_TOL",
    "STACK_SIDECAR_NAMES",
    "choose_slice_axis",
    "derive_patient_id",
    "read_dicom_series",
    "read_image_stack",
    "read_nifti_scan",
    "read_scan",
]

"""Accepted values of ``modality`` (case-insensitive)."""

REL_TOL = 0.01
"""Relative tolerance (1 %) of every slice-step and spacing comparison."""

STACK_SIDECAR_NAMES = ("stack.yaml", "slices.yaml")
"""File names of the image-stack sidecar, in order of preference."""

IMAGE_STACK_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg")
"""File suffixes (lower case) read as 2-D slices of an image stack."""

_NIFTI_SUFFIXES = (".nii.gz", ".nii")
_DICOM_FILE_SUFFIXES = (".dcm", ".dicom", ".ima")
_UNSAFE_ID_CHARS = re.compile(r"[^A-Za-z0-9._-]")
_STACK_KEYS = ("pixel_spacing_mm", "slice_thickness_mm", "slice_gap_mm", "order", "modality")
_LUMA_WEIGHTS = np.array([0.299, 0.587, 0.114])  # ITU-R 601-2, as Pillow's convert("L")


# --------------------------------------------------------------------------- public API


def read_scan(
    path: str | os.PathLike[str],
    *,
    modality: str | None = None,
    patient_id: str | None = None,
    series_uid: str | None = None,
    slice_thickness_mm: float | None = None,
    slice_gap_mm: float | None = None,
) -> Scan:
    """Read one patient's slice stack from a NIfTI file or a folder.

    Parameters
    ----------
    path : str or path-like
        A ``.nii``/``.nii.gz`` file, a DICOM series folder, or a folder of
        2-D PNG/TIFF/JPEG slices with a ``stack.yaml`` sidecar.
    modality : {"t2", "flair", "t1c"}, optional
        MR sequence (case-insensitive). ``None`` means ``"t2"``, except for
        an image stack whose sidecar names a modality.
    patient_id : str, optional
        Folder-safe id; default :func:`derive_patient_id` of ``path``.
    series_uid : str, optional
        SeriesInstanceUID to pick when a DICOM folder holds several series.
    slice_thickness_mm, slice_gap_mm : float, optional
        Override the nominal slice thickness (> 0) and inter-slice gap
        (>= 0) that the input states (see the module docstring).

    Returns
    -------
    Scan
        float32 ``(z, y, x)`` image with its geometry and source grid.

    Raises
    ------
    InputError
        If the path is missing, unsupported or unreadable, holds a single
        2-D image, a constant volume or non-finite values, or if a parameter
        is invalid. The message names the file and the problem.
    """
    p = Path(path)
    if not p.exists():
        raise InputError("no such file or folder", str(p))
    mod = None if modality is None else _check_modality(modality)
    pid = derive_patient_id(p) if patient_id is None else validate_patient_id(patient_id)
    thickness = _check_override("slice_thickness_mm", slice_thickness_mm, allow_zero=False)
    gap = _check_override("slice_gap_mm", slice_gap_mm, allow_zero=True)
    common = {"patient_id": pid, "slice_thickness_mm": thickness, "slice_gap_mm": gap}

    if p.is_file():
        lower = p.name.lower()
        if lower.endswith(_NIFTI_SUFFIXES):
            return read_nifti_scan(p, modality=mod or "t2", **common)
        if lower.endswith(IMAGE_STACK_SUFFIXES + _DICOM_FILE_SUFFIXES):
            raise InputError(
                "a single 2-D image was given where a stack is needed: at least 2 slices "
                "are needed (give the folder of a DICOM series, or a folder of 2-D slices "
                f"with {STACK_SIDECAR_NAMES[0]})",
                str(p),
            )
        raise InputError(
            f"unsupported file type {''.join(p.suffixes) or '(no extension)'!r}: give a NIfTI "
            "file (.nii, .nii.gz), a DICOM series folder, or a folder of 2-D "
            f"PNG/TIFF/JPEG slices with {STACK_SIDECAR_NAMES[0]}",
            str(p),
        )
    if not p.is_dir():
        raise InputError("neither a regular file nor a folder", str(p))
    if any((p / name).is_file() for name in STACK_SIDECAR_NAMES):
        return read_image_stack(p, modality=mod, **common)
    try:
        return read_dicom_series(p, modality=mod or "t2", series_uid=series_uid, **common)
    except _NoDicomImagesError:
        if _list_stack_images(p):
            raise InputError(
                f"missing sidecar {STACK_SIDECAR_NAMES[0]} (or {STACK_SIDECAR_NAMES[1]}) "
                "describing pixel_spacing_mm, slice_thickness_mm and slice_gap_mm of the "
                "2-D slices in this folder",
                str(p / STACK_SIDECAR_NAMES[0]),
            ) from None
        raise


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
    for suffix in _NIFTI_SUFFIXES:
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


# --------------------------------------------------------------------------- NIfTI


def read_nifti_scan(
    path: str | os.PathLike[str],
    *,
    modality: str = "t2",
    patient_id: str | None = None,
    slice_thickness_mm: float | None = None,
    slice_gap_mm: float | None = None,
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
    modality, patient_id, slice_thickness_mm, slice_gap_mm
        As for :func:`read_scan`.

    Returns
    -------
    Scan

    Raises
    ------
    InputError
        Unreadable file, unsupported dimensionality, a single 2-D image,
        a singular affine, a constant or non-finite volume, or a sidecar that
        contradicts the image.
    """
    import nibabel as nib

    p = Path(path)
    where = str(p)
    mod = _check_modality(modality)
    pid = derive_patient_id(p) if patient_id is None else validate_patient_id(patient_id)
    thickness_override = _check_override("slice_thickness_mm", slice_thickness_mm, allow_zero=False)
    gap_override = _check_override("slice_gap_mm", slice_gap_mm, allow_zero=True)
    if not p.is_file():
        raise InputError("no such file", where)
    try:
        img = nib.load(where)
    except Exception as exc:  # nibabel raises many types for a bad file
        raise InputError(f"not a readable NIfTI image ({_describe(exc)})", where) from exc
    if not isinstance(img, nib.Nifti1Image | nib.Nifti2Image):
        raise InputError(f"not a NIfTI image (nibabel read it as {type(img).__name__})", where)

    shape = tuple(int(s) for s in img.shape)
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

    affine = np.asarray(img.affine, dtype=np.float64)
    if not np.all(np.isfinite(affine)) or abs(np.linalg.det(affine[:3, :3])) < 1e-12:
        raise InputError("the image affine is singular or not finite", where)
    try:
        data = np.asarray(img.get_fdata(dtype=np.float32), dtype=np.float32)
    except Exception as exc:
        raise InputError(f"cannot read the voxel data ({_describe(exc)})", where) from exc
    data = data.reshape(shape)

    s = choose_slice_axis(affine)
    axes = (*[a for a in range(3) if a != s], s)
    image = np.ascontiguousarray(data.transpose(axes[::-1]))  # (z, y, x)
    _check_volume(image, where)
    scan_affine = affine.copy()
    for k in range(3):
        scan_affine[:, k] = affine[:, axes[k]]
    spacing = np.linalg.norm(affine[:3, :3], axis=0)
    dx, dy, step = (float(spacing[a]) for a in axes)

    file_thickness = _read_bids_sidecar(p, step)
    thickness, gap = _resolve_thickness(
        step, file_thickness, thickness_override, gap_override, where
    )
    return Scan(
        image=image,
        affine=scan_affine,
        pixel_spacing_mm=(dy, dx),
        slice_step_mm=step,
        slice_thickness_mm=thickness,
        slice_gap_mm=gap,
        modality=mod,
        patient_id=pid,
        source=f"NIfTI file {p.name}, {image.shape[0]} slices along voxel axis {s}",
        source_grid=SourceGrid(shape=shape, affine=affine, axes=axes),
    )


def _bids_sidecar_path(p: Path) -> Path:
    lower = p.name.lower()
    for suffix in _NIFTI_SUFFIXES:
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


# --------------------------------------------------------------------------- DICOM


class _NoDicomImagesError(InputError):
    """A folder without any DICOM image (lets read_scan suggest a stack sidecar)."""


def read_dicom_series(
    folder: str | os.PathLike[str],
    *,
    modality: str = "t2",
    patient_id: str | None = None,
    series_uid: str | None = None,
    slice_thickness_mm: float | None = None,
    slice_gap_mm: float | None = None,
) -> Scan:
    """Read one DICOM series from a folder (not recursive) as a `Scan`.

    Files that are not DICOM (README, DICOMDIR without pixels, ...) are
    skipped. Images are grouped by ``SeriesInstanceUID``, sorted by their
    position along the slice normal, checked for a uniform step (1 %) and
    rescaled with ``RescaleSlope``/``RescaleIntercept`` (see the module
    docstring for the affine).

    Parameters
    ----------
    folder : str or path-like
        Folder holding the series' files.
    modality, patient_id, slice_thickness_mm, slice_gap_mm
        As for :func:`read_scan`.
    series_uid : str, optional
        Required when the folder holds several series.

    Returns
    -------
    Scan

    Raises
    ------
    InputError
        No images, several series without ``series_uid``, an unknown
        ``series_uid``, a single image, inconsistent geometry, duplicate
        positions, a non-uniform step, undecodable pixels, or a constant or
        non-finite volume.
    """
    import pydicom
    from pydicom.errors import InvalidDicomError

    d = Path(folder)
    mod = _check_modality(modality)
    pid = derive_patient_id(d) if patient_id is None else validate_patient_id(patient_id)
    thickness_override = _check_override("slice_thickness_mm", slice_thickness_mm, allow_zero=False)
    gap_override = _check_override("slice_gap_mm", slice_gap_mm, allow_zero=True)
    if not d.is_dir():
        raise InputError("no such folder", str(d))

    series: dict[str, list[tuple[Path, Any]]] = {}
    for f in sorted(d.iterdir()):
        if not f.is_file():
            continue
        try:
            ds = pydicom.dcmread(f, defer_size="4 KB", force=False)
        except InvalidDicomError:
            continue  # not a DICOM file: skipped silently
        except Exception as exc:
            raise InputError(f"unreadable DICOM file ({_describe(exc)})", str(f)) from exc
        if "PixelData" not in ds:
            continue  # DICOMDIR, structured report, presentation state, ...
        series.setdefault(str(ds.get("SeriesInstanceUID", "")), []).append((f, ds))

    if not series:
        raise _NoDicomImagesError(f"no DICOM images found in {d}")
    if series_uid is None and len(series) > 1:
        raise InputError(
            f"{len(series)} DICOM series found; choose one with series_uid: "
            + _describe_series(series),
            str(d),
        )
    if series_uid is not None and series_uid not in series:
        raise InputError(
            f"series_uid {series_uid!r} not found; available: " + _describe_series(series),
            str(d),
        )
    items = series[series_uid if series_uid is not None else next(iter(series))]
    if len(items) < 2:
        raise InputError(
            f"a single 2-D image ({items[0][0].name}) in the DICOM series: at least 2 "
            "slices are needed",
            str(d),
        )
    geometry = [_dicom_geometry(f, ds) for f, ds in items]
    image, affine, step, pixel_spacing, first = _assemble_dicom(items, geometry, d)
    _check_volume(image, str(d))
    file_thickness = None
    raw_thickness = first.get("SliceThickness", None)
    if raw_thickness not in (None, ""):
        try:
            value = float(raw_thickness)
        except (TypeError, ValueError):
            value = float("nan")
        if math.isfinite(value) and value > 0:
            file_thickness = value
    thickness, gap = _resolve_thickness(
        step, file_thickness, thickness_override, gap_override, str(d)
    )
    nz, ny, nx = image.shape
    return Scan(
        image=image,
        affine=affine,
        pixel_spacing_mm=pixel_spacing,
        slice_step_mm=step,
        slice_thickness_mm=thickness,
        slice_gap_mm=gap,
        modality=mod,
        patient_id=pid,
        source=f"DICOM series in folder {d.name}, {nz} slices",
        source_grid=SourceGrid(shape=(nx, ny, nz), affine=affine, axes=(0, 1, 2)),
    )


def _describe_series(series: dict[str, list[tuple[Path, Any]]]) -> str:
    parts = []
    for uid, items in series.items():
        description = str(items[0][1].get("SeriesDescription", "") or "")
        parts.append(f"{uid or '(no SeriesInstanceUID)'} ({description!r}, {len(items)} files)")
    return "; ".join(parts)


def _dicom_geometry(f: Path, ds: Any) -> dict[str, Any]:
    """Read and check the geometry tags of one image."""
    values: dict[str, Any] = {}
    for tag, n in (
        ("ImageOrientationPatient", 6),
        ("ImagePositionPatient", 3),
        ("PixelSpacing", 2),
    ):
        raw = ds.get(tag, None)
        if raw is None or raw == "":
            raise InputError(f"missing {tag}: cannot place the slice in space", str(f))
        try:
            arr = np.array([float(v) for v in raw], dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InputError(f"invalid {tag} {raw!r}", str(f)) from exc
        if arr.shape != (n,) or not np.all(np.isfinite(arr)):
            raise InputError(f"{tag} must hold {n} finite numbers, got {list(raw)}", str(f))
        values[tag] = arr
    if np.any(values["PixelSpacing"] <= 0):
        raise InputError(f"PixelSpacing must be positive, got {values['PixelSpacing']}", str(f))
    row_cos, col_cos = values["ImageOrientationPatient"][:3], values["ImageOrientationPatient"][3:]
    nr, nc = np.linalg.norm(row_cos), np.linalg.norm(col_cos)
    if abs(nr - 1) > 1e-2 or abs(nc - 1) > 1e-2 or abs(row_cos @ col_cos) > 1e-2:
        raise InputError(
            "ImageOrientationPatient does not hold two orthogonal unit vectors", str(f)
        )
    frames = ds.get("NumberOfFrames", 1)
    if int(frames or 1) > 1:
        raise InputError(
            f"a multi-frame image ({frames} frames) is not supported: give one file per slice",
            str(f),
        )
    if int(ds.get("SamplesPerPixel", 1) or 1) != 1:
        raise InputError("a colour DICOM image is not supported (SamplesPerPixel != 1)", str(f))
    try:
        rows, cols = int(ds.Rows), int(ds.Columns)
    except (AttributeError, TypeError, ValueError) as exc:
        raise InputError("missing or invalid Rows/Columns", str(f)) from exc
    values["row_cos"] = row_cos / nr
    values["col_cos"] = col_cos / nc
    values["shape"] = (rows, cols)
    return values


def _assemble_dicom(
    items: list[tuple[Path, Any]], geometry: list[dict[str, Any]], folder: Path
) -> tuple[np.ndarray, np.ndarray, float, tuple[float, float], Any]:
    """Sort, check and stack the slices; return image, RAS affine, step, (dy, dx), first ds."""
    g0, f0 = geometry[0], items[0][0]
    for (f, _), g in zip(items[1:], geometry[1:], strict=True):
        if g["shape"] != g0["shape"]:
            raise InputError(
                f"image size {g['shape']} differs from {g0['shape']} of {f0.name}", str(f)
            )
        if np.max(np.abs(g["ImageOrientationPatient"] - g0["ImageOrientationPatient"])) > 1e-3:
            raise InputError(
                f"ImageOrientationPatient differs from that of {f0.name}: all slices of a "
                "series must share one orientation",
                str(f),
            )
        if np.any(np.abs(g["PixelSpacing"] - g0["PixelSpacing"]) > 1e-3 * g0["PixelSpacing"]):
            raise InputError(
                f"PixelSpacing {g['PixelSpacing']} differs from {g0['PixelSpacing']} of {f0.name}",
                str(f),
            )
    row_cos, col_cos = g0["row_cos"], g0["col_cos"]
    normal = np.cross(row_cos, col_cos)
    normal /= np.linalg.norm(normal)
    positions = np.array([g["ImagePositionPatient"] for g in geometry])
    dist = positions @ normal
    order = np.argsort(dist, kind="stable")
    dist, positions = dist[order], positions[order]
    names = [items[i][0].name for i in order]
    steps = np.diff(dist)
    for i, s in enumerate(steps):
        if s < 1e-3:
            raise InputError(
                f"duplicate slice position: {names[i]} and {names[i + 1]} lie at the same "
                f"position ({dist[i]:.4f} mm along the slice normal); several images per "
                "position (echoes, time points) are not supported",
                str(folder),
            )
    expected = float(np.median(steps))
    bad = np.flatnonzero(np.abs(steps - expected) > REL_TOL * expected)
    if bad.size:
        i = int(bad[0])
        raise InputError(
            f"non-uniform slice step: between {names[i]} and {names[i + 1]} the step is "
            f"{steps[i]:.4g} mm, expected {expected:.4g} mm (the median step; tolerance 1 %)",
            str(folder),
        )
    step = float((dist[-1] - dist[0]) / (len(dist) - 1))
    in_plane = (positions - positions[0]) - np.outer(dist - dist[0], normal)
    drift = float(np.max(np.linalg.norm(in_plane, axis=1)))
    dy, dx = (float(v) for v in g0["PixelSpacing"])
    if drift > 0.1 * min(dx, dy):
        raise InputError(
            f"slice positions drift by up to {drift:.3g} mm within the slice plane (a "
            "sheared stack, e.g. gantry tilt), which is not supported",
            str(folder),
        )

    slices = []
    for i in order:
        f, ds = items[i]
        try:
            pixels = np.asarray(ds.pixel_array, dtype=np.float64)
        except Exception as exc:
            raise InputError(f"cannot decode the pixel data ({_describe(exc)})", str(f)) from exc
        if pixels.shape != g0["shape"]:
            raise InputError(
                f"pixel data of shape {pixels.shape} does not match Rows x Columns {g0['shape']}",
                str(f),
            )
        slope = _dicom_float(ds, "RescaleSlope", 1.0, f)
        intercept = _dicom_float(ds, "RescaleIntercept", 0.0, f)
        slices.append(pixels * slope + intercept)
    image = np.stack(slices).astype(np.float32)

    lps = np.eye(4)
    lps[:3, 0] = row_cos * dx
    lps[:3, 1] = col_cos * dy
    lps[:3, 2] = normal * step
    lps[:3, 3] = positions[0]
    affine = np.diag([-1.0, -1.0, 1.0, 1.0]) @ lps
    return image, affine, step, (dy, dx), items[int(order[0])][1]


def _dicom_float(ds: Any, tag: str, default: float, f: Path) -> float:
    raw = ds.get(tag, None)
    if raw is None or raw == "":
        return default
    try:
        value = float(raw)
    except (TypeError, ValueError) as exc:
        raise InputError(f"invalid {tag} {raw!r}", str(f)) from exc
    if not math.isfinite(value):
        raise InputError(f"{tag} must be finite, got {raw!r}", str(f))
    return value


# --------------------------------------------------------------------------- image stack


def read_image_stack(
    folder: str | os.PathLike[str],
    *,
    modality: str | None = None,
    patient_id: str | None = None,
    slice_thickness_mm: float | None = None,
    slice_gap_mm: float | None = None,
) -> Scan:
    """Read a folder of 2-D PNG/TIFF/JPEG slices with a YAML sidecar as a `Scan`.

    The sidecar ``stack.yaml`` (or ``slices.yaml``) holds
    ``pixel_spacing_mm`` (``[dy, dx]`` or one number), ``slice_thickness_mm``,
    ``slice_gap_mm``, and optionally ``order`` (file names, first = lowest z;
    default: natural sort of the image file names, so ``2`` before ``10``)
    and ``modality``. RGB slices are converted to luminance
    ``0.299 R + 0.587 G + 0.114 B``. The affine is
    ``diag(-dx, -dy, thickness + gap, 1)`` (see the module docstring).

    Parameters
    ----------
    folder : str or path-like
        The folder of slices.
    modality : str, optional
        Overrides the sidecar's ``modality``; default ``"t2"``.
    patient_id, slice_thickness_mm, slice_gap_mm
        As for :func:`read_scan`; the overrides make the sidecar keys
        optional.

    Returns
    -------
    Scan

    Raises
    ------
    InputError
        Missing or invalid sidecar or key, fewer than 2 slices, an
        unreadable image, slices of different sizes, or a constant or
        non-finite volume.
    """
    import yaml

    d = Path(folder)
    pid = derive_patient_id(d) if patient_id is None else validate_patient_id(patient_id)
    thickness_override = _check_override("slice_thickness_mm", slice_thickness_mm, allow_zero=False)
    gap_override = _check_override("slice_gap_mm", slice_gap_mm, allow_zero=True)
    if not d.is_dir():
        raise InputError("no such folder", str(d))
    present = [d / n for n in STACK_SIDECAR_NAMES if (d / n).is_file()]
    if not present:
        raise InputError(
            "missing sidecar: the folder needs it to give pixel_spacing_mm, "
            "slice_thickness_mm and slice_gap_mm",
            str(d / STACK_SIDECAR_NAMES[0]),
        )
    if len(present) > 1:
        raise InputError(
            f"both {STACK_SIDECAR_NAMES[0]} and {STACK_SIDECAR_NAMES[1]} are present: keep one",
            str(d),
        )
    sidecar = present[0]
    where = str(sidecar)
    try:
        meta = yaml.safe_load(sidecar.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise InputError(f"not a readable YAML sidecar ({_describe(exc)})", where) from exc
    if not isinstance(meta, dict):
        raise InputError("the sidecar must hold a mapping of keys to values", where)
    unknown = sorted(str(k) for k in meta if k not in _STACK_KEYS)
    if unknown:
        raise InputError(
            f"unknown key(s) {', '.join(unknown)}; allowed: {', '.join(_STACK_KEYS)}", where
        )

    if "pixel_spacing_mm" not in meta:
        raise InputError("missing key 'pixel_spacing_mm' ([dy, dx] in mm)", where)
    raw_spacing = meta["pixel_spacing_mm"]
    if isinstance(raw_spacing, list | tuple):
        if len(raw_spacing) != 2:
            raise InputError(
                f"key 'pixel_spacing_mm' must be [dy, dx] or one number, got {raw_spacing!r}",
                where,
            )
        dy = _positive_number(raw_spacing[0], "pixel_spacing_mm", where)
        dx = _positive_number(raw_spacing[1], "pixel_spacing_mm", where)
    else:
        dy = dx = _positive_number(raw_spacing, "pixel_spacing_mm", where)

    if thickness_override is not None:
        thickness = thickness_override
    elif "slice_thickness_mm" in meta:
        thickness = _positive_number(meta["slice_thickness_mm"], "slice_thickness_mm", where)
    else:
        raise InputError("missing key 'slice_thickness_mm'", where)
    if gap_override is not None:
        gap = gap_override
    elif "slice_gap_mm" in meta:
        gap = _positive_number(meta["slice_gap_mm"], "slice_gap_mm", where, allow_zero=True)
    else:
        raise InputError("missing key 'slice_gap_mm' (0 for contiguous slices)", where)

    if modality is not None:
        mod = _check_modality(modality)
    elif meta.get("modality") is not None:
        mod = _check_modality(meta["modality"], where=where)
    else:
        mod = "t2"

    files = _stack_files(d, meta.get("order"), where)
    if not files:
        raise InputError(f"no 2-D slice images ({'/'.join(IMAGE_STACK_SUFFIXES)}) found", str(d))
    if len(files) < 2:
        raise InputError(
            f"a single 2-D image ({files[0].name}): at least 2 slices are needed", str(d)
        )
    slices = [_read_slice(files[0])]
    for f in files[1:]:
        arr = _read_slice(f)
        if arr.shape != slices[0].shape:
            raise InputError(
                f"slice size {arr.shape[1]}x{arr.shape[0]} (width x height) differs from "
                f"{slices[0].shape[1]}x{slices[0].shape[0]} of {files[0].name}",
                str(f),
            )
        slices.append(arr)
    image = np.stack(slices).astype(np.float32)
    _check_volume(image, str(d))
    step = thickness + gap
    affine = np.diag([-dx, -dy, step, 1.0])
    nz, ny, nx = image.shape
    return Scan(
        image=image,
        affine=affine,
        pixel_spacing_mm=(dy, dx),
        slice_step_mm=step,
        slice_thickness_mm=thickness,
        slice_gap_mm=gap,
        modality=mod,
        patient_id=pid,
        source=f"image stack in folder {d.name}, {nz} slices",
        source_grid=SourceGrid(shape=(nx, ny, nz), affine=affine, axes=(0, 1, 2)),
    )


def _natural_key(name: str) -> list[Any]:
    return [(0, int(t), "") if t.isdigit() else (1, 0, t.lower()) for t in re.split(r"(\d+)", name)]


def _list_stack_images(d: Path) -> list[Path]:
    return [
        f
        for f in d.iterdir()
        if f.is_file()
        and not f.name.startswith(".")
        and f.name.lower().endswith(IMAGE_STACK_SUFFIXES)
    ]


def _stack_files(d: Path, order: Any, where: str) -> list[Path]:
    if order is None:
        return sorted(_list_stack_images(d), key=lambda f: _natural_key(f.name))
    if not isinstance(order, list) or not all(isinstance(n, str) for n in order):
        raise InputError("key 'order' must be a list of file names", where)
    if len(set(order)) != len(order):
        dup = sorted({n for n in order if order.count(n) > 1})
        raise InputError(f"key 'order' lists {', '.join(dup)} more than once", where)
    files = []
    for name in order:
        if Path(name).name != name or name in (".", ".."):
            raise InputError(f"key 'order': {name!r} must be a plain file name", where)
        f = d / name
        if not f.is_file():
            raise InputError(f"key 'order': file {name!r} does not exist", where)
        files.append(f)
    return files


def _read_slice(f: Path) -> np.ndarray:
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(f) as im:
            if getattr(im, "n_frames", 1) > 1:
                raise InputError(
                    f"a multi-page image ({im.n_frames} pages): save one slice per file", str(f)
                )
            mode = im.mode
            if mode in ("RGB", "RGBA", "P", "PA", "CMYK", "YCbCr", "LAB", "HSV"):
                rgb = np.asarray(im.convert("RGB"), dtype=np.float64)
                arr = rgb @ _LUMA_WEIGHTS
            elif mode == "LA":
                arr = np.asarray(im.getchannel("L"), dtype=np.float64)
            else:
                arr = np.asarray(im, dtype=np.float64)
    except InputError:
        raise
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as exc:
        raise InputError(f"not a readable 2-D image ({_describe(exc)})", str(f)) from exc
    if arr.ndim != 2:
        raise InputError(f"expected a 2-D grayscale or RGB image, got shape {arr.shape}", str(f))
    return arr


# --------------------------------------------------------------------------- shared checks


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
    bound = "a non-negative" if allow_zero else "a positive"
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise InputError(f"{name} must be {bound} number of mm, got {value!r}", where)
    v = float(value)
    if not math.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise InputError(f"{name} must be {bound} number of mm, got {value!r}", where)
    return v


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
