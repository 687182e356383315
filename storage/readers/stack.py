"""Image-stack reader: a folder of 2-D PNG/TIFF/JPEG slices with a YAML sidecar -> `Scan`."""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Any

import numpy as np

from tumor3d.constants import YAML_MAX_BYTES
from tumor3d.errors import ConfigError, InputError
from tumor3d.imaging.identity import validate_patient_id
from tumor3d.imaging.scan import Scan, SourceGrid
from tumor3d.safe_yaml import load_yaml
from tumor3d.storage.readers.common import (
    MAX_VOXELS_DEFAULT,
    _check_override,
    _check_volume,
    _describe,
    _positive_number,
    check_max_voxels,
    check_modality,
    check_voxel_count,
    derive_patient_id,
)
from tumor3d.storage.readers.options import ReadOptions
from tumor3d.storage.readers.registry import register_reader
from tumor3d.validation import short_repr

__all__ = ["IMAGE_STACK_SUFFIXES", "STACK_SIDECAR_NAMES", "declared_modality", "read_image_stack"]

STACK_SIDECAR_NAMES = ("stack.yaml", "slices.yaml")
"""File names of the image-stack sidecar, in order of preference."""

IMAGE_STACK_SUFFIXES = (".png", ".tif", ".tiff", ".jpg", ".jpeg")
"""File suffixes (lower case) read as 2-D slices of an image stack."""

_STACK_KEYS = ("pixel_spacing_mm", "slice_thickness_mm", "slice_gap_mm", "order", "modality")
_LUMA_WEIGHTS = np.array([0.299, 0.587, 0.114])  # ITU-R 601-2, as Pillow's convert("L")


def read_image_stack(
    folder: str | os.PathLike[str],
    *,
    modality: str | None = None,
    patient_id: str | None = None,
    slice_thickness_mm: float | None = None,
    slice_gap_mm: float | None = None,
    max_voxels: int = MAX_VOXELS_DEFAULT,
) -> Scan:
    """Read a folder of 2-D PNG/TIFF/JPEG slices with a YAML sidecar as a `Scan`.

    The sidecar ``stack.yaml`` (or ``slices.yaml``) holds
    ``pixel_spacing_mm`` (a list ``dy, dx`` or one number), ``slice_thickness_mm``,
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
    max_voxels : int
        Refuse a stack whose first image's width x height x number of
        files exceeds this, before any pixel is decoded.

    Returns
    -------
    Scan

    Raises
    ------
    InputError
        Missing or invalid sidecar or key, fewer than 2 slices, more voxels
        than ``max_voxels``, an unreadable image (or a decompression bomb),
        slices of different sizes, or a constant or non-finite volume.
    """
    d = Path(folder)
    limit = check_max_voxels(max_voxels)
    pid = derive_patient_id(d) if patient_id is None else validate_patient_id(patient_id)
    thickness_override = _check_override("slice_thickness_mm", slice_thickness_mm, allow_zero=False)
    gap_override = _check_override("slice_gap_mm", slice_gap_mm, allow_zero=True)
    if not d.is_dir():
        raise InputError("no such folder", str(d))
    meta, where = _read_sidecar(d)

    if "pixel_spacing_mm" not in meta:
        raise InputError(
            "missing key 'pixel_spacing_mm' (the row and column spacing dy, dx in mm, "
            "or one number)",
            where,
        )
    raw_spacing = meta["pixel_spacing_mm"]
    if isinstance(raw_spacing, list | tuple):
        if len(raw_spacing) != 2:
            raise InputError(
                "key 'pixel_spacing_mm' must be a list of two numbers (dy, dx) or one number, "
                f"got {short_repr(raw_spacing)}",
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
        mod = check_modality(modality)
    elif meta.get("modality") is not None:
        mod = check_modality(meta["modality"], where=where)
    else:
        mod = "t2"

    files = _stack_files(d, meta.get("order"), where)
    if not files:
        raise InputError(f"no 2-D slice images ({'/'.join(IMAGE_STACK_SUFFIXES)}) found", str(d))
    if len(files) < 2:
        raise InputError(
            f"a single 2-D image ({files[0].name}): at least 2 slices are needed", str(d)
        )
    width, height = _slice_size(files[0])
    check_voxel_count((width, height, len(files)), limit, str(d))
    first, depth = _read_slice(files[0])
    slices = [first]
    for f in files[1:]:
        arr, this_depth = _read_slice(f)
        if this_depth != depth:  # gray levels on another scale: a tumour lost silently
            raise InputError(
                f"saved with {this_depth} gray levels, {files[0].name} with {depth}: save "
                "every slice with the same bit depth",
                str(f),
            )
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
        orientation_stated=False,  # 2-D images: LPS by convention
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


def _slice_size(f: Path) -> tuple[int, int]:
    """``(width, height)`` from an image's header, without decoding its pixels."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(f) as im:
            return int(im.size[0]), int(im.size[1])
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError) as exc:
        raise InputError(f"not a readable 2-D image ({_describe(exc)})", str(f)) from exc
    except Image.DecompressionBombError as exc:
        raise InputError(f"refused as a decompression bomb ({_describe(exc)})", str(f)) from None


#: The scale of a PIL image mode's gray levels (slices of one stack must share it).
_DEPTHS = {"1": "1-bit", "I;16": "16-bit", "I;16B": "16-bit", "I;16L": "16-bit",
           "I;16N": "16-bit", "I": "32-bit integer", "F": "32-bit float"}  # fmt: skip


def _depth(mode: str) -> str:
    """The bit depth of a PIL mode's values, in words (8-bit: gray, colour, palette).

    >>> _depth("L"), _depth("RGB"), _depth("I;16B"), _depth("F")
    ('8-bit', '8-bit', '16-bit', '32-bit float')
    """
    return _DEPTHS.get(mode, "8-bit")


def _read_slice(f: Path) -> tuple[np.ndarray, str]:
    """A slice's gray levels (float64, rows x columns) and its bit depth in words."""
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
    except Image.DecompressionBombError as exc:
        raise InputError(f"refused as a decompression bomb ({_describe(exc)})", str(f)) from None
    if arr.ndim != 2:
        raise InputError(f"expected a 2-D grayscale or RGB image, got shape {arr.shape}", str(f))
    return arr, _depth(mode)


def _has_sidecar(folder: Path) -> bool:
    return any((folder / name).is_file() for name in STACK_SIDECAR_NAMES)


def _read_sidecar(d: Path) -> tuple[dict, str]:
    """The stack folder's sidecar as a mapping of its known keys, and its path.

    Raises
    ------
    InputError
        No sidecar or two, too large, not YAML, not a mapping, or an unknown key.
    """
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
        size = sidecar.stat().st_size
        if size > YAML_MAX_BYTES:
            raise InputError(
                f"a sidecar of {size:,} bytes, more than the {YAML_MAX_BYTES:,} allowed", where
            )
        meta = load_yaml(sidecar.read_text(encoding="utf-8"), source=where)
    except ConfigError as exc:
        raise InputError(f"not a readable YAML sidecar ({exc.problem})", where) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"not a readable YAML sidecar ({_describe(exc)})", where) from exc
    if not isinstance(meta, dict):
        raise InputError("the sidecar must hold a mapping of keys to values", where)
    unknown = sorted(str(k) for k in meta if k not in _STACK_KEYS)
    if unknown:
        raise InputError(
            f"unknown key(s) {', '.join(unknown)}; allowed: {', '.join(_STACK_KEYS)}", where
        )
    return meta, where


def declared_modality(path: str | os.PathLike[str]) -> str | None:
    """The modality an image-stack folder's sidecar names (its ``modality`` key), else ``None``.

    A file, a DICOM folder or a stack whose sidecar has no ``modality`` declares
    none. The command line and the flows take it before their default (``"t2"``),
    so a documented key is not overridden by a default.

    Raises
    ------
    InputError
        The sidecar cannot be read, or names an unknown modality (naming the sidecar).

    Examples
    --------
    >>> import tempfile
    >>> d = Path(tempfile.mkdtemp())
    >>> _ = (d / "stack.yaml").write_text("modality: FLAIR")
    >>> declared_modality(d), declared_modality(d / "stack.yaml")
    ('flair', None)
    """
    d = Path(path)
    if not d.is_dir() or not _has_sidecar(d):
        return None
    meta, where = _read_sidecar(d)
    value = meta.get("modality")
    return None if value is None else check_modality(value, where=where)


def _missing_sidecar(folder: Path) -> InputError | None:
    """Images but no sidecar (and no DICOM): name the sidecar to write."""
    if not _list_stack_images(folder):
        return None
    return InputError(
        f"missing sidecar {STACK_SIDECAR_NAMES[0]} (or {STACK_SIDECAR_NAMES[1]}) "
        "describing pixel_spacing_mm, slice_thickness_mm and slice_gap_mm of the "
        "2-D slices in this folder",
        str(folder / STACK_SIDECAR_NAMES[0]),
    )


@register_reader(
    "stack",
    accepts=f"a folder of 2-D PNG/TIFF/JPEG slices with {STACK_SIDECAR_NAMES[0]}",
    claims=_has_sidecar,
    slice_suffixes=IMAGE_STACK_SUFFIXES,
    hint=_missing_sidecar,
)
def _read_stack(path: Path, options: ReadOptions) -> Scan:
    return read_image_stack(path, modality=options.modality, **options.common())
