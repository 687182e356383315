"""The volumes the page embeds.

The scan cropped to the brain and tumour, in 8 bits, subsampled when too large.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from tumor3d.errors import InputError
from tumor3d.validation import check_affine

#: Margin kept around the brain and tumour when the image is cropped (mm).
CROP_MARGIN_MM = 10.0
#: Largest image the page embeds (voxels); beyond it the finest axis is subsampled.
MAX_VIEWER_VOXELS = 4_000_000


def _mask(arr: object, shape: tuple[int, ...], name: str) -> np.ndarray:
    a = np.asarray(arr)
    if a.shape != shape:
        raise InputError(f"{name} has shape {a.shape}, the image {shape}: they must match")
    return a.astype(bool)


def viewer_volume(
    image_zyx: np.ndarray,
    affine: np.ndarray,
    masks: Sequence[np.ndarray],
    *,
    margin_mm: float = CROP_MARGIN_MM,
    max_voxels: int = MAX_VIEWER_VOXELS,
) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """The display copy of an image and its masks: cropped, subsampled, 8-bit.

    Parameters
    ----------
    image_zyx : ndarray, shape (z, y, x)
        The MR image (any real dtype). Not modified.
    affine : (4, 4) array_like
        Maps ``(x, y, z, 1)`` voxel indices to RAS mm.
    masks : sequence of ndarray, shape (z, y, x)
        Masks on the image's grid; the crop box is that of their union
        (the whole image when they are all empty) plus ``margin_mm``.
    margin_mm : float
        Margin around the box, mm (>= 0).
    max_voxels : int
        Largest number of voxels kept: beyond it the axis with the finest
        spacing (after subsampling) is subsampled by one more step, until it fits.

    Returns
    -------
    image : uint8 ndarray, shape (z', y', x')
        Intensities scaled linearly between the 0.5th and 99.5th
        percentiles of the cropped image (clipped; non-finite values are 0).
    masks : list of bool ndarray, shape (z', y', x')
    affine : (4, 4) float64 ndarray
        Maps the new ``(x, y, z, 1)`` indices to the same RAS mm.

    Examples
    --------
    >>> img = np.arange(4 * 50 * 60, dtype=float).reshape(4, 50, 60)
    >>> m = np.zeros(img.shape, bool); m[1:3, 20:30, 10:20] = True
    >>> small, (m2,), aff = viewer_volume(img, np.eye(4), [m], margin_mm=2)
    >>> small.shape, int(m2.sum()) == int(m.sum()), aff[:3, 3].tolist()
    ((4, 14, 14), True, [8.0, 18.0, 0.0])
    """
    img = np.asarray(image_zyx)
    if img.ndim != 3 or min(img.shape) < 1:
        raise InputError(f"the image must be a non-empty 3-D array, got shape {img.shape}")
    if not (np.issubdtype(img.dtype, np.number) or img.dtype == bool):
        raise InputError(f"the image must hold numbers, got dtype {img.dtype}")
    aff = check_affine(affine)
    if (
        isinstance(margin_mm, bool)
        or not isinstance(margin_mm, (int, float))
        or not np.isfinite(margin_mm)
        or margin_mm < 0
    ):
        raise InputError(f"margin_mm must be a finite number >= 0, got {margin_mm!r}")
    if isinstance(max_voxels, bool) or not isinstance(max_voxels, int) or max_voxels < 1:
        raise InputError(f"max_voxels must be a positive integer, got {max_voxels!r}")
    ms = [_mask(m, img.shape, f"mask {i} of {len(masks)}") for i, m in enumerate(masks)]
    # spacing of the (z, y, x) axes: lengths of the affine's columns (z, y, x) = (2, 1, 0)
    spacing = np.linalg.norm(aff[:3, [2, 1, 0]], axis=0)
    union = np.zeros(img.shape, bool)
    for m in ms:
        union |= m
    lo = np.zeros(3, np.int64)
    hi = np.array(img.shape, np.int64)
    if union.any():
        pad = np.ceil(margin_mm / spacing).astype(np.int64)
        for ax in range(3):
            other = tuple(a for a in range(3) if a != ax)
            idx = np.flatnonzero(union.any(axis=other))
            lo[ax] = max(0, idx[0] - pad[ax])
            hi[ax] = min(img.shape[ax], idx[-1] + 1 + pad[ax])
    step = np.ones(3, np.int64)
    while int(np.prod(-(-(hi - lo) // step))) > max_voxels:
        finest = int(np.argmin(np.where(-(-(hi - lo) // step) > 1, spacing * step, np.inf)))
        step[finest] += 1
    box = tuple(slice(int(a), int(b), int(s)) for a, b, s in zip(lo, hi, step, strict=True))
    crop = np.asarray(img[box], dtype=np.float64)
    finite = np.isfinite(crop)
    if finite.any():
        p_lo, p_hi = np.percentile(crop[finite], [0.5, 99.5])
    else:
        p_lo = p_hi = 0.0
    scale = 255.0 / (p_hi - p_lo) if p_hi > p_lo else 0.0
    scaled = np.where(finite, (np.where(finite, crop, p_lo) - p_lo) * scale, 0.0)
    u8 = np.clip(np.rint(scaled), 0, 255).astype(np.uint8)
    # new index (x, y, z) -> old index lo + step * new (xyz order: reverse of zyx)
    sub = np.eye(4)
    sub[:3, :3] = np.diag(step[::-1].astype(np.float64))
    sub[:3, 3] = lo[::-1]
    return u8, [np.ascontiguousarray(m[box]) for m in ms], aff @ sub
