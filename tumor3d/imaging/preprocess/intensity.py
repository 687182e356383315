"""Gray levels to 8 bits: the percentile window of :func:`to_uint8` and the masked background.

The input checks of :mod:`tumor3d.imaging.preprocess` live here too.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from tumor3d.errors import InputError


def _check_volume(image: object, name: str = "image") -> np.ndarray:
    arr = np.asarray(image)
    if arr.ndim != 3:
        raise InputError(f"{name} must be a 3-D (z, y, x) array, got {arr.ndim} dimension(s)")
    if arr.dtype == bool or not (
        np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)
    ):
        raise InputError(f"{name} must hold real numbers, got dtype {arr.dtype}")
    if min(arr.shape) == 0:
        raise InputError(f"{name} is empty (shape {arr.shape})")
    if np.issubdtype(arr.dtype, np.floating) and not np.all(np.isfinite(arr)):
        raise InputError(f"{name} contains NaN or infinite values")
    return arr


def _check_percentiles(window_percentiles: object) -> tuple[float, float]:
    try:
        lo, hi = (float(p) for p in window_percentiles)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise InputError(
            f"window_percentiles must be a pair of numbers, got {window_percentiles!r}"
        ) from None
    if not (0.0 <= lo < hi <= 100.0):
        raise InputError(f"window_percentiles must satisfy 0 <= low < high <= 100, got {(lo, hi)}")
    return lo, hi


def to_uint8(image: np.ndarray, *, window_percentiles=(0.5, 99.5)) -> np.ndarray:
    """Convert a volume to 8-bit slices with one intensity window for the whole volume.

    The paper works on 8-bit slices; MR volumes are usually float or 16-bit.
    The window ``[lo, hi]`` is the pair of ``window_percentiles`` of the
    *foreground* intensities, and ``I = round(255 (x - lo) / (hi - lo))``
    clipped to ``[0, 255]``. One window for the whole volume keeps the gray
    levels of a tissue comparable across slices.

    Foreground = voxels strictly greater than the volume minimum. This
    excludes the air (0 in magnitude images) and also the non-zero constant
    background of z-scored BraTS volumes, which would otherwise dominate the
    percentiles. The background therefore always maps to 0. If the
    foreground percentiles coincide (for instance a two-valued volume), the
    full range ``[min, max]`` is used instead.

    Parameters
    ----------
    image : (z, y, x) ndarray of real numbers
        The volume; it is not modified.
    window_percentiles : (float, float)
        Percentiles (0-100) of the foreground intensities mapped to 0 and 255.

    Returns
    -------
    (z, y, x) ndarray of uint8

    Raises
    ------
    InputError
        If ``image`` is not 3-D, not real, contains NaN/inf or is constant,
        or the percentiles are not ``0 <= low < high <= 100``.

    Examples
    --------
    >>> v = np.zeros((1, 2, 3)); v[0, 0] = [1.0, 2.0, 3.0]
    >>> to_uint8(v, window_percentiles=(0, 100))[0]
    array([[  0, 128, 255],
           [  0,   0,   0]], dtype=uint8)
    """
    arr = _check_volume(image)
    lo_p, hi_p = _check_percentiles(window_percentiles)
    return _to_uint8(arr, lo_p, hi_p)


#: Values within this share of the volume's intensity range of the background value are
#: background: the rounding of a resampling (a weighted mean of equal values is equal up
#: to a few ulps), far below any intensity difference between tissues.
BACKGROUND_TOLERANCE = 1e-6


#: The intensity range of that tolerance is robust: between these quantiles of the
#: volume (of at most ``_RANGE_SAMPLE`` voxels drawn with a fixed seed), so that a few extreme
#: voxels do not widen it. With the plain minimum and maximum, one voxel at 1e7 in a
#: skull-stripped BraTS FLAIR (range about 10) made a tolerance of 10: the whole brain
#: became "background" and the run said "no tumour found" (measured by an audit).
BACKGROUND_RANGE_QUANTILES = (0.001, 0.999)


_RANGE_SAMPLE = 200_000


class MaskedBackground(NamedTuple):
    """:func:`masked_background`: the value, its tolerance, the share and the voxels."""

    value: float
    tolerance: float
    share: float
    mask: np.ndarray  # (z, y, x) bool: the voxels within ``tolerance`` of ``value``


def masked_background(arr: np.ndarray) -> MaskedBackground:
    """The constant background a mask left in a volume (:class:`MaskedBackground`).

    Skull stripping sets every voxel outside the brain to one value: the
    volume's minimum (0 in BraTS T2, -3.16 in the z-scored BraTS FLAIR), or 0
    below a brain z-scored to negative values too. The candidates are the
    minimum and the most frequent value of the volume's in-plane border (the
    background fills the corners); the one that more voxels hold, within
    ``BACKGROUND_TOLERANCE`` of the intensity range (the rounding of a
    resampling: a volume resampled with linear interpolation holds the mask
    value up to a few ulps; the range between the
    ``BACKGROUND_RANGE_QUANTILES``, so that an extreme voxel does not widen
    it), is the background. ``share`` is the share of the
    volume that holds it (81-89 % on the BraTS volumes, 2-6 % on raw heads,
    whose air carries noise), ``mask`` those voxels.

    >>> v = np.zeros((2, 4, 4)); v[:, 1:3, 1:3] = [[-1.0, 2.0], [3.0, -2.0]]
    >>> bg = masked_background(v)  # 0 is the background, not the minimum -2
    >>> bg.value, bg.share, int(bg.mask.sum())
    (0.0, 0.75, 24)
    """
    lo = float(arr.min())
    flat = arr.reshape(-1)
    if flat.size > _RANGE_SAMPLE:  # a seeded random sample: a stride could alias with a row
        flat = flat[np.random.default_rng(0).integers(0, flat.size, _RANGE_SAMPLE)]
    q_lo, q_hi = np.quantile(flat.astype(np.float64), BACKGROUND_RANGE_QUANTILES)
    tol = BACKGROUND_TOLERANCE * float(q_hi - q_lo)
    border = np.concatenate(
        [arr[:, 0, :].ravel(), arr[:, -1, :].ravel(), arr[:, :, 0].ravel(), arr[:, :, -1].ravel()]
    )
    values, counts = np.unique(border, return_counts=True)
    best = None
    for candidate in (lo, float(values[np.argmax(counts)])):
        mask = np.abs(arr - candidate) <= tol
        share = float(np.count_nonzero(mask)) / arr.size
        if best is None or share > best.share:
            best = MaskedBackground(candidate, tol, share, mask)
    return best


def _to_uint8(arr: np.ndarray, lo_p: float, hi_p: float, background=None) -> np.ndarray:
    """The 8-bit window; ``background`` = :func:`masked_background` of ``arr`` if known."""
    bg = masked_background(arr) if background is None else background
    foreground = arr[~bg.mask]
    if foreground.size == 0:
        raise InputError("image is constant: no foreground to set an intensity window from")
    lo, hi = np.percentile(foreground.astype(np.float64), [lo_p, hi_p])
    if not hi > lo:
        lo, hi = float(arr.min()), float(arr.max())
    return _window_u8(arr, float(lo), 255.0 / (float(hi) - float(lo)))


#: Voxels per block of :func:`_window_u8` (a 512 KiB float64 buffer that stays in cache).
_WINDOW_BLOCK = 1 << 16


def _window_u8(arr: np.ndarray, lo: float, scale: float) -> np.ndarray:
    """``floor(clip((x - lo) * scale, 0, 255) + 0.5)`` as uint8, block by block.

    The same float64 operations in the same order as the whole-array numpy
    expression (hence the same bits), in place on one small reused buffer
    instead of four volume-sized float64 temporaries.
    """
    flat = arr.reshape(-1)
    out = np.empty(flat.size, dtype=np.uint8)
    buf = np.empty(min(_WINDOW_BLOCK, flat.size), dtype=np.float64)
    for start in range(0, flat.size, _WINDOW_BLOCK):
        part = flat[start : start + _WINDOW_BLOCK]
        b = buf[: part.size]
        b[...] = part
        b -= lo
        b *= scale
        np.clip(b, 0.0, 255.0, out=b)
        b += 0.5
        np.floor(b, out=b)
        out[start : start + part.size] = b
    return out.reshape(arr.shape)
