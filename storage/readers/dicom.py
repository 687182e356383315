"""DICOM reader: one series from a folder of single-frame images -> `Scan`."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from tumor3d.constants import (
    DICOM_DUPLICATE_POSITION_MM,
    DICOM_IN_PLANE_DRIFT_FRACTION,
    DICOM_ORIENTATION_TOL,
    DICOM_PIXEL_SPACING_REL_TOL,
    DICOM_UNIT_VECTOR_TOL,
    SHEAR_TOL,
)
from tumor3d.errors import InputError
from tumor3d.imaging.identity import validate_patient_id
from tumor3d.imaging.scan import Scan, SourceGrid
from tumor3d.storage.readers.common import (
    MAX_VOXELS_DEFAULT,
    REL_TOL,
    _check_override,
    _check_volume,
    _describe,
    _resolve_thickness,
    check_max_voxels,
    check_modality,
    check_voxel_count,
    derive_patient_id,
    in_plane_axes,
    working_orientation,
)
from tumor3d.storage.readers.options import ReadOptions
from tumor3d.storage.readers.registry import NotThisFormat, register_reader

__all__ = ["DICOM_FILE_SUFFIXES", "NOT_DICOM_SUFFIXES", "read_dicom_series"]

DICOM_FILE_SUFFIXES = (".dcm", ".dicom", ".ima")
"""File suffixes (lower case) of single DICOM files."""


#: Suffixes (lower case) of files that are evidently not DICOM and are ignored
#: in a series folder (notes, sidecars, previews, archives).
NOT_DICOM_SUFFIXES = (
    ".txt", ".md", ".rst", ".json", ".xml", ".csv", ".tsv", ".yaml", ".yml", ".html",
    ".htm", ".pdf", ".log", ".ini", ".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp",
    ".gif", ".nii", ".gz", ".zip", ".tar", ".nrrd", ".nhdr", ".mha", ".mhd", ".raw",
)  # fmt: skip
_TEXT_PROBE_BYTES = 4096


class _NoDicomImagesError(NotThisFormat):
    """A folder without any DICOM image (lets read_scan suggest a stack sidecar)."""


def read_dicom_series(
    folder: str | os.PathLike[str],
    *,
    modality: str = "t2",
    patient_id: str | None = None,
    series_uid: str | None = None,
    slice_thickness_mm: float | None = None,
    slice_gap_mm: float | None = None,
    skip_unreadable: bool = False,
    max_voxels: int = MAX_VOXELS_DEFAULT,
) -> Scan:
    """Read one DICOM series from a folder (not recursive) as a `Scan`.

    Files that are evidently not DICOM are ignored: hidden files, files with
    a suffix in :data:`NOT_DICOM_SUFFIXES`, text files (the first 4 KB are
    UTF-8 without NUL bytes, e.g. a ``README``), and DICOM files without
    pixel data (DICOMDIR, structured reports). Any other file that cannot be
    parsed as DICOM (random bytes, a truncated header) is *unreadable*: by
    default the read stops with an error naming every such file; with
    ``skip_unreadable=True`` they are skipped and listed in
    ``Scan.skipped_files`` (and counted in ``Scan.source``). Images are
    grouped by ``SeriesInstanceUID``, sorted by their position along the
    slice normal, checked for a uniform step (1 %) and
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
    skip_unreadable : bool
        Skip files that cannot be read as DICOM instead of stopping (the
        CLI's ``--skip-unreadable-dicom``); they are listed in
        ``Scan.skipped_files``.
    max_voxels : int
        Refuse a series whose Rows x Columns x number of images exceeds
        this, before any pixel data is decoded.

    Returns
    -------
    Scan

    Raises
    ------
    InputError
        Unreadable files (without ``skip_unreadable``), no images, several
        series without ``series_uid``, an unknown
        ``series_uid``, a single image, inconsistent geometry, duplicate
        positions, a non-uniform step, undecodable pixels, or a constant or
        non-finite volume.
    """
    import pydicom
    from pydicom.errors import InvalidDicomError

    d = Path(folder)
    mod = check_modality(modality)
    pid = derive_patient_id(d) if patient_id is None else validate_patient_id(patient_id)
    thickness_override = _check_override("slice_thickness_mm", slice_thickness_mm, allow_zero=False)
    gap_override = _check_override("slice_gap_mm", slice_gap_mm, allow_zero=True)
    limit = check_max_voxels(max_voxels)
    if not d.is_dir():
        raise InputError("no such folder", str(d))

    series: dict[str, list[tuple[Path, Any]]] = {}
    unreadable: list[tuple[str, str]] = []  # (file name, reason)
    for f in sorted(d.iterdir()):
        if not f.is_file() or _evidently_not_dicom(f):
            continue
        try:
            ds = pydicom.dcmread(f, defer_size="4 KB", force=False)
        except InvalidDicomError:
            unreadable.append((f.name, "not a DICOM file (no DICOM header)"))
            continue
        except Exception as exc:  # pydicom raises many types for a damaged file
            unreadable.append((f.name, _describe(exc)))
            continue
        if "PixelData" not in ds:
            damage = _missing_pixels_problem(ds)
            if damage:
                unreadable.append((f.name, damage))
            continue  # DICOMDIR, structured report, presentation state, ...
        series.setdefault(str(ds.get("SeriesInstanceUID", "")), []).append((f, ds))
    if unreadable and not skip_unreadable:
        raise _unreadable_error(unreadable, d)

    if not series:
        raise _NoDicomImagesError(f"no DICOM images found in {d}")
    if series_uid is None and len(series) > 1:
        raise InputError(
            f"{len(series)} DICOM series found; choose one with --series-uid "
            "(series_uid=...): " + _describe_series(series),
            str(d),
        )
    if series_uid is not None and series_uid not in series:
        raise InputError(
            f"series {series_uid!r} (--series-uid) not found; available: "
            + _describe_series(series),
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
    check_voxel_count((*geometry[0]["shape"], len(items)), limit, str(d))
    pixels: dict[Path, np.ndarray] = {}
    undecodable: list[tuple[str, str]] = []
    for f, ds in items:
        try:
            pixels[f] = np.asarray(ds.pixel_array, dtype=np.float64)
        except Exception as exc:  # truncated or damaged pixel data, unknown codec
            undecodable.append((f.name, f"cannot decode the pixel data ({_describe(exc)[:160]})"))
    if undecodable:
        if not skip_unreadable:
            raise _unreadable_error(undecodable, d)
        unreadable += undecodable
        kept = [k for k, (f, _) in enumerate(items) if f in pixels]
        items, geometry = [items[k] for k in kept], [geometry[k] for k in kept]
        if len(items) < 2:
            raise InputError(
                f"fewer than 2 readable images remain in the DICOM series after skipping "
                f"{len(unreadable)} unreadable file(s)",
                str(d),
            )
    skipped = tuple(sorted(name for name, _ in unreadable))
    image, affine, step, pixel_spacing, first = _assemble_dicom(items, geometry, pixels, d)
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
    # the in-plane order of a volume file (in_plane_axes): rows and columns swapped when
    # the series stores them the other way round; the source grid keeps the files' order
    axes = (*in_plane_axes(affine, 2), 2)
    source_affine = affine
    if axes != (0, 1, 2):
        image = np.ascontiguousarray(image.transpose(0, 2, 1))
        affine = affine[:, [1, 0, 2, 3]]
        pixel_spacing = (pixel_spacing[1], pixel_spacing[0])
    scan = Scan(
        image=image,
        affine=affine,
        pixel_spacing_mm=pixel_spacing,
        slice_step_mm=step,
        slice_thickness_mm=thickness,
        slice_gap_mm=gap,
        modality=mod,
        patient_id=pid,
        source=f"DICOM series in folder {d.name}, {nz} slices"
        + _tilt_note(affine, step)
        + (f", {len(skipped)} unreadable file(s) skipped" if skipped else ""),
        source_grid=SourceGrid(shape=(nx, ny, nz), affine=source_affine, axes=axes),
        skipped_files=skipped,
    )
    return working_orientation(scan)


def _tilt_note(affine: np.ndarray, step: float) -> str:
    column = float(np.linalg.norm(affine[:3, 2]))
    if column - step <= SHEAR_TOL * column:
        return ""
    return f" (gantry tilt: slice planes {step:.4g} mm apart, slice-axis column {column:.4g} mm)"


def _unreadable_error(unreadable: list[tuple[str, str]], d: Path) -> InputError:
    """One line naming every unreadable file (the first 10, then a count)."""
    shown = "; ".join(f"{name}: {why}" for name, why in unreadable[:10])
    more = f"; and {len(unreadable) - 10} more" if len(unreadable) > 10 else ""
    return InputError(
        f"{len(unreadable)} file(s) could not be read as DICOM: {shown}{more}. Remove "
        "them, or skip them explicitly with --skip-unreadable-dicom (skip_unreadable=True)",
        str(d),
    )


def _missing_pixels_problem(ds: Any) -> str | None:
    """Why a DICOM object without pixel data is damaged, or None for a non-image object."""
    sop = ds.get("SOPClassUID", None) or ds.get("file_meta", {}).get(
        "MediaStorageSOPClassUID", None
    )
    if not sop:
        return "a DICOM header without SOP class or pixel data (truncated or damaged)"
    name = getattr(sop, "name", str(sop))
    if "Image Storage" in name:
        return f"a {name} object without pixel data (truncated?)"
    return None  # DICOMDIR, structured report, presentation state, ...


def _evidently_not_dicom(f: Path) -> bool:
    """Hidden files, known non-DICOM suffixes and text files are not slices."""
    name = f.name.lower()
    if name.startswith(".") or name.endswith(NOT_DICOM_SUFFIXES):
        return True
    try:
        with open(f, "rb") as fh:
            head = fh.read(_TEXT_PROBE_BYTES)
    except OSError:
        return False  # reported as unreadable by pydicom
    if not head or b"\0" in head:
        return False  # empty (a truncated slice?) or binary: let pydicom judge it
    try:
        head.decode("utf-8")
    except UnicodeDecodeError as exc:
        # a multi-byte character cut at the probe's end is still text
        return exc.start >= len(head) - 3
    return True


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
    if (
        abs(nr - 1) > DICOM_UNIT_VECTOR_TOL
        or abs(nc - 1) > DICOM_UNIT_VECTOR_TOL
        or abs(row_cos @ col_cos) > DICOM_UNIT_VECTOR_TOL
    ):
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
    items: list[tuple[Path, Any]],
    geometry: list[dict[str, Any]],
    pixels: dict[Path, np.ndarray],
    folder: Path,
) -> tuple[np.ndarray, np.ndarray, float, tuple[float, float], Any]:
    """Sort, check and stack the slices; return image, RAS affine, step, (dy, dx), first ds."""
    g0, f0 = geometry[0], items[0][0]
    for (f, _), g in zip(items[1:], geometry[1:], strict=True):
        if g["shape"] != g0["shape"]:
            raise InputError(
                f"image size {g['shape']} differs from {g0['shape']} of {f0.name}", str(f)
            )
        if (
            np.max(np.abs(g["ImageOrientationPatient"] - g0["ImageOrientationPatient"]))
            > DICOM_ORIENTATION_TOL
        ):
            raise InputError(
                f"ImageOrientationPatient differs from that of {f0.name}: all slices of a "
                "series must share one orientation",
                str(f),
            )
        if np.any(
            np.abs(g["PixelSpacing"] - g0["PixelSpacing"])
            > DICOM_PIXEL_SPACING_REL_TOL * g0["PixelSpacing"]
        ):
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
        if s < DICOM_DUPLICATE_POSITION_MM:
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
    tolerance = DICOM_IN_PLANE_DRIFT_FRACTION * min(dx, dy)
    slice_column = normal * step
    if drift > tolerance:
        # A sheared stack (gantry tilt): the slices must still lie on one
        # straight line, the slice column is then the mean position step
        # (not perpendicular to the slices) and the step stays the distance
        # between slice planes.
        slice_column = (positions[-1] - positions[0]) / (len(positions) - 1)
        k = (dist - dist[0]) / step  # 0, 1, 2, ... (the step is uniform)
        off_line = positions - positions[0] - np.outer(k, slice_column)
        worst = float(np.max(np.linalg.norm(off_line, axis=1)))
        if worst > tolerance:
            raise InputError(
                f"slice positions drift by up to {drift:.3g} mm within the slice plane and "
                f"not along a straight line (off by up to {worst:.3g} mm): a uniformly "
                "tilted (gantry-tilt) stack is supported, an irregular one is not",
                str(folder),
            )

    slices = []
    for i in order:
        f, ds = items[i]
        values = pixels[f]
        if values.shape != g0["shape"]:
            raise InputError(
                f"pixel data of shape {values.shape} does not match Rows x Columns {g0['shape']}",
                str(f),
            )
        slope = _dicom_float(ds, "RescaleSlope", 1.0, f)
        intercept = _dicom_float(ds, "RescaleIntercept", 0.0, f)
        slices.append(values * slope + intercept)
    image = np.stack(slices).astype(np.float32)

    lps = np.eye(4)
    lps[:3, 0] = row_cos * dx
    lps[:3, 1] = col_cos * dy
    lps[:3, 2] = slice_column
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


@register_reader(
    "dicom",
    accepts="a DICOM series folder",
    fallback=True,
    slice_suffixes=DICOM_FILE_SUFFIXES,
)
def _read_dicom(path: Path, options: ReadOptions) -> Scan:
    return read_dicom_series(
        path,
        modality=options.modality or "t2",
        series_uid=options.series_uid,
        skip_unreadable=options.skip_unreadable,
        **options.common(),
    )
