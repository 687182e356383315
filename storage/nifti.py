"""Deterministic NIfTI-1 encoding and decoding of volumes and masks.

:func:`encode_nifti` turns a voxel array and its affine into gzip-compressed
NIfTI-1 bytes that are identical for identical inputs (gzip ``mtime=0``, no
file name, a fixed ``descrip``), so that the bytes can be content-addressed. The
deflate is ISA-L's (``isal.igzip``, standard gzip that every reader opens): on MR
volumes 19-30 times faster than zlib's level 6, for volumes up to 20 % larger and
smooth probability maps up to 2 times (reports/benchmarks.md, "NIfTI compression").
The bytes are the same for a given ISA-L build and processor family (ISA-L has
code of its own per family): where they differ, a content-addressed artifact is
stored twice and its dependants recomputed, never read wrong.
sform and qform both hold the affine (code 1, scanner, unless the input's own
codes are kept: ``SourceGrid.xform_codes``), units are mm. :func:`placed_affine`
reads where every NIfTI file is placed in the world.

The ``*_to_source_nifti_bytes`` helpers write Scan-grid ``(z, y, x)``
arrays back in the input's own voxel grid and affine through
:class:`tumor3d.imaging.scan.SourceGrid`, so that a mask overlays its input voxel
for voxel in any viewer.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
from isal import igzip

from tumor3d.constants import MAX_VOXELS_DEFAULT
from tumor3d.errors import InputError
from tumor3d.imaging.scan import SourceGrid
from tumor3d.validation import check_affine, check_int

__all__ = [
    "NIFTI_DTYPES",
    "decode_nifti",
    "differing_qform",
    "encode_nifti",
    "mask_to_source_nifti_bytes",
    "placed_affine",
    "probability_for_storage",
    "read_nifti",
    "volume_to_source_nifti_bytes",
]

NIFTI_DTYPES = (np.dtype(np.uint8), np.dtype(np.int16), np.dtype(np.float32))
"""Voxel types :func:`encode_nifti` writes."""

PROBABILITY_LEVELS = 255
"""A stored probability map holds multiples of ``1 / PROBABILITY_LEVELS``."""

#: The NIfTI spatial units (``xyzt_units``) and their length in mm; "unknown" is read as
#: mm, as every NIfTI reader does. Meters and microns are converted, as ITK, MINC's
#: nii2mnc and Connectome Workbench do (nibabel's ``affine`` ignores the field).
UNIT_MM = {"mm": 1.0, "unknown": 1.0, "meter": 1000.0, "micron": 0.001}


def xform_codes(header: Any) -> tuple[int, int]:
    """A NIfTI header's ``(sform_code, qform_code)``."""
    return int(header["sform_code"]), int(header["qform_code"])


def placed_affine(img: Any) -> np.ndarray:
    """The affine (voxel index -> RAS mm) of a loaded NIfTI image, as tumor3d places it.

    nibabel's ``img.affine`` (the sform, else the qform, else for a header that states
    no orientation, codes 0, nibabel's guess: LAS, centred), its lengths converted to mm
    by the header's spatial unit (:data:`UNIT_MM`). The one reading of a NIfTI file's
    placement: the scan readers, a given mask and the evaluation's references.

    >>> import nibabel as nib
    >>> img = nib.Nifti1Image(np.zeros((2, 2, 2), np.float32), np.diag([2.0, 3.0, 4.0, 1.0]))
    >>> img.header.set_xyzt_units("micron")
    >>> placed_affine(img).diagonal().tolist()
    [0.002, 0.003, 0.004, 1.0]
    """
    return _in_mm(img.header, img.affine)


def _in_mm(header: Any, affine: Any) -> np.ndarray:
    """A copy of ``affine`` with its lengths in mm, by ``header``'s spatial unit."""
    out = np.array(affine, dtype=np.float64)
    out[:3, :] *= UNIT_MM.get(str(header.get_xyzt_units()[0]), 1.0)
    return out


def differing_qform(img: Any, affine: np.ndarray) -> np.ndarray | None:
    """A loaded NIfTI image's qform in mm where it differs from its placed ``affine``.

    None unless both forms are stated and differ; ``affine`` is :func:`placed_affine`'s.
    nibabel (and so :func:`placed_affine`) reads the sform; ITK reads the qform unless
    the sform code is 1, so a file whose two forms differ (an sform aligned to another
    image beside the scanner's qform, as registration tools write) is placed differently
    by the two (``SourceGrid.qform``).
    """
    sform_code, qform_code = xform_codes(img.header)
    if not (sform_code and qform_code):
        return None
    qform = _in_mm(img.header, img.header.get_qform())
    return None if np.allclose(qform, affine, atol=1e-4) else qform


_DESCRIP = b"tumor3d"
#: ISA-L's level 1 (of 0-3): its levels 1 and 2 compress alike; 3 is 4 times slower for
#: files 4 % smaller; 0 is as fast and 20 % larger.
_GZIP_LEVEL = 1
_GZIP_MAGIC = b"\x1f\x8b"


def encode_nifti(
    array: np.ndarray,
    affine: np.ndarray,
    *,
    dtype: np.dtype | type | str,
    label: bool = False,
    codes: tuple[int, int] = (1, 1),
    qform: np.ndarray | None = None,
) -> bytes:
    """Encode a 3-D voxel array as gzip-compressed NIfTI-1 bytes, deterministically.

    Parameters
    ----------
    array : ndarray, shape (i, j, k)
        Voxel values in the file's own axis order (NIfTI order: the first
        axis is the fastest-varying voxel index ``i``). Not modified.
    affine : (4, 4) array_like
        Maps the voxel index ``(i, j, k, 1)`` to RAS mm; stored as sform and
        qform. Its last row must be ``(0, 0, 0, 1)``.
    dtype : {uint8, int16, float32}
        Stored voxel type. For the integer types the values must be whole
        numbers within the type's range (nothing is rounded or clipped).
    label : bool
        A mask: the header's intent is ``NIFTI_INTENT_LABEL`` (each value an
        index into a set of labels, here 0 = background, 1 = the structure).
    codes : tuple of int
        ``(sform_code, qform_code)``: 1 (scanner) unless an input's own codes are kept
        (``SourceGrid.xform_codes``); with both 0 the file states no orientation, and
        a reader places it by its voxel size alone, as it places such an input.
    qform : (4, 4) array_like, optional
        Stored as the qform instead of ``affine`` (an input's own qform where it differs
        from its sform: :meth:`tumor3d.imaging.scan.SourceGrid.qform_of`).

    Returns
    -------
    bytes
        A ``.nii.gz`` file's content; the same inputs give the same bytes.

    Raises
    ------
    ValueError
        Unsupported dtype, not 3-D, a bad affine, or values that the dtype
        cannot hold exactly.
    """
    import nibabel as nib

    dt = np.dtype(dtype)
    if dt not in NIFTI_DTYPES:
        raise ValueError(
            f"dtype must be one of {', '.join(str(d) for d in NIFTI_DTYPES)}, got {dt}"
        )
    arr = np.asarray(array)
    if arr.ndim != 3:
        raise ValueError(f"array must be 3-D, got shape {arr.shape}")
    aff = _check_affine(affine)
    data = _cast_exactly(arr, dt)
    header = nib.Nifti1Header()
    header.set_data_dtype(dt)
    img = nib.Nifti1Image(data, aff, header=header)
    img.set_sform(aff, code=int(codes[0]))
    img.set_qform(aff if qform is None else _check_affine(qform), code=int(codes[1]))
    img.header.set_xyzt_units(xyz="mm")
    if label:
        img.header.set_intent("label")
    img.header["descrip"] = _DESCRIP
    raw = img.to_bytes()
    return igzip.compress(raw, compresslevel=_GZIP_LEVEL, mtime=0)


def decode_nifti(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """Decode NIfTI-1 bytes (gzip-compressed or not) into ``(array, affine)``.

    Parameters
    ----------
    data : bytes
        Content of a ``.nii`` or ``.nii.gz`` file.

    Returns
    -------
    array : ndarray
        Voxels in the file's axis order and stored type (scaled to float if
        the header sets ``scl_slope``).
    affine : (4, 4) float64 ndarray
        nibabel's affine (sform, else qform).

    Raises
    ------
    InputError
        If the bytes are not a NIfTI-1 image.
    """
    import nibabel as nib

    try:
        raw = igzip.decompress(data) if bytes(data[:2]) == _GZIP_MAGIC else bytes(data)
        img = nib.Nifti1Image.from_bytes(raw)
        array = np.asanyarray(img.dataobj).copy()
    except Exception as exc:
        raise InputError(f"not NIfTI-1 data ({type(exc).__name__}: {exc})") from exc
    return array, np.array(img.affine, dtype=np.float64)


def read_nifti(
    path: str | os.PathLike[str], *, max_voxels: int = MAX_VOXELS_DEFAULT
) -> tuple[np.ndarray, np.ndarray]:
    """Read a NIfTI file into ``(array, affine)`` (see :func:`decode_nifti`).

    Parameters
    ----------
    path : str or path-like
        A ``.nii`` or ``.nii.gz`` file.
    max_voxels : int
        Refuse a file whose header declares more voxels (checked before any
        voxel is read; default 512 million).

    Returns
    -------
    array : ndarray
        Voxels in the file's axis order.
    affine : (4, 4) float64 ndarray

    Raises
    ------
    InputError
        If the file is missing, declares more than ``max_voxels`` voxels,
        or is not a readable NIfTI image.
    """
    import nibabel as nib

    limit = check_int(max_voxels, "max_voxels", minimum=1)
    p = Path(path)
    if not p.is_file():
        raise InputError("no such file", str(p))
    try:
        img = nib.load(str(p))
        if not isinstance(img, nib.Nifti1Image):
            raise TypeError(f"nibabel read it as {type(img).__name__}")
        n = int(np.prod([int(v) for v in img.shape]))
        if n > limit:
            raise InputError(
                f"the header declares {' x '.join(str(v) for v in img.shape)} = {n:,} voxels, "
                f"more than the limit of {limit:,} (max_voxels)",
                str(p),
            )
        array = np.asanyarray(img.dataobj).copy()
    except InputError:
        raise
    except Exception as exc:
        raise InputError(
            f"not a readable NIfTI image ({type(exc).__name__}: {exc})", str(p)
        ) from exc
    return array, placed_affine(img)


def probability_for_storage(probability: np.ndarray) -> np.ndarray:
    """A probability map rounded to multiples of 1/255, as float32, to store and publish.

    A model's probability differs in its last bits from voxel to voxel (the
    background is about 1e-5, not 0), which gzip cannot compress: the map of
    a 240 x 240 x 155 BraTS FLAIR took 29 MB as float32, 0.5 MB rounded. The
    rounding moves no value by more than 1/510 and keeps the side of 0.5
    (0.5 is a rounding boundary of 255 levels: a value rounds to 128/255 or
    above exactly when it is at least 0.5). float32, not uint8 with a scale
    factor, so that every reader sees probabilities in [0, 1] as they are.

    Parameters
    ----------
    probability : ndarray
        Values in [0, 1], any shape. Not modified.

    Returns
    -------
    ndarray of float32, the same shape

    Examples
    --------
    >>> probability_for_storage(np.array([0.0, 1e-5, 0.499, 0.5, 1.0])).tolist()
    [0.0, 0.0, 0.49803921580314636, 0.501960813999176, 1.0]
    """
    p = np.clip(np.asarray(probability, dtype=np.float64), 0.0, 1.0)
    return (np.round(p * PROBABILITY_LEVELS) / PROBABILITY_LEVELS).astype(np.float32)


def mask_to_source_nifti_bytes(mask_zyx: np.ndarray, grid: SourceGrid) -> bytes:
    """Write a Scan-grid mask in the input's own voxel grid and affine.

    Parameters
    ----------
    mask_zyx : ndarray, shape (z, y, x)
        Boolean mask, or integer labels in ``0..255``, on the `Scan` grid.
    grid : SourceGrid
        ``scan.source_grid`` of the scan the mask belongs to.

    Returns
    -------
    bytes
        uint8 ``.nii.gz`` content with the source's shape and affine.

    Raises
    ------
    ValueError
        If the mask's shape does not fit the grid or its values are not
        whole numbers in ``0..255``.
    """
    m = np.asarray(mask_zyx)
    if m.ndim != 3:
        raise ValueError(f"mask must be 3-D (z, y, x), got shape {m.shape}")
    source = grid.to_source(m)
    return encode_nifti(
        source, grid.affine, dtype=np.uint8, label=True, codes=grid.xform_codes,
        qform=grid.qform_of(grid.affine),
    )  # fmt: skip


def volume_to_source_nifti_bytes(
    array_zyx: np.ndarray,
    affine_xyz: np.ndarray,
    grid: SourceGrid,
    *,
    dtype: np.dtype | type | str,
) -> bytes:
    """Write a volume on another grid of the scan's world space in source axis order.

    The axes (and affine columns) are permuted as the source's are (see
    :meth:`tumor3d.imaging.scan.SourceGrid.to_source_with_affine`); no resampling,
    so every voxel keeps its world position.

    Parameters
    ----------
    array_zyx : ndarray, shape (z, y, x)
        The volume (e.g. a finely interpolated mask).
    affine_xyz : (4, 4) array_like
        Maps ``(x, y, z, 1)`` of ``array_zyx`` to RAS mm.
    grid : SourceGrid
        ``scan.source_grid`` of the scan the volume derives from.
    dtype : {uint8, int16, float32}
        Stored voxel type (see :func:`encode_nifti`); uint8 is a mask (its
        intent ``NIFTI_INTENT_LABEL``).

    Returns
    -------
    bytes
        ``.nii.gz`` content.
    """
    arr = np.asarray(array_zyx)
    if arr.ndim != 3:
        raise ValueError(f"array must be 3-D (z, y, x), got shape {arr.shape}")
    aff = _check_affine(affine_xyz)
    source, source_affine = grid.to_source_with_affine(arr, aff)
    # the input's codes; but on another grid than the input's, codes 0 would place the
    # volume by its own shape, not on the input: an input without orientation gets the
    # scanner code there, with the affine it was read by (nibabel's guess)
    on_input_grid = source.shape == grid.shape and np.allclose(source_affine, grid.affine)
    codes = grid.xform_codes if on_input_grid or any(grid.xform_codes) else (1, 1)
    return encode_nifti(
        source, source_affine, dtype=dtype, label=np.dtype(dtype) == np.uint8, codes=codes,
        qform=grid.qform_of(source_affine),
    )  # fmt: skip


def _check_affine(affine: np.ndarray) -> np.ndarray:
    """A finite, invertible 4x4 affine (see :func:`tumor3d.validation.check_affine`)."""
    return check_affine(affine)


def _cast_exactly(arr: np.ndarray, dt: np.dtype) -> np.ndarray:
    """Cast to ``dt``, refusing any value the type cannot hold exactly."""
    if arr.dtype == dt:
        return arr
    if arr.dtype == bool:
        return arr.astype(dt)
    if dt.kind == "f":
        if arr.dtype.kind not in "biuf":
            raise ValueError(f"cannot store {arr.dtype} values as {dt}")
        return arr.astype(dt)
    if arr.dtype.kind not in "iuf":
        raise ValueError(f"cannot store {arr.dtype} values as {dt}")
    info = np.iinfo(dt)
    if arr.size:
        if arr.dtype.kind == "f":
            if not np.all(np.isfinite(arr)):
                raise ValueError(f"non-finite values cannot be stored as {dt}")
            if not np.array_equal(arr, np.round(arr)):
                raise ValueError(f"values with a fractional part cannot be stored as {dt}")
        lo, hi = arr.min(), arr.max()
        if lo < info.min or hi > info.max:
            raise ValueError(
                f"values in [{lo}, {hi}] do not fit {dt} (range [{info.min}, {info.max}])"
            )
    return arr.astype(dt)
