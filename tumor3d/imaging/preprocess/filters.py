"""Steps 1-3 of :mod:`tumor3d.imaging.preprocess`: median filter, unsharp kernel, equalisation.

Each applied to the whole ``(z, y, x)`` stack with a kernel of depth 1, so
slices never mix.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from tumor3d.errors import InputError


def unsharp_kernel(alpha: float) -> np.ndarray:
    r"""MATLAB's ``fspecial('unsharp', alpha)`` kernel [A1].

    .. math::
        h = \frac{1}{\alpha + 1}
        \begin{pmatrix} -\alpha & \alpha - 1 & -\alpha \\
        \alpha - 1 & \alpha + 5 & \alpha - 1 \\
        -\alpha & \alpha - 1 & -\alpha \end{pmatrix}

    i.e. the identity minus MATLAB's ``fspecial('laplacian', alpha)``
    ("the negative of the 2-D Laplacian"); its entries sum to 1.

    Parameters
    ----------
    alpha : float
        Shape of the Laplacian, in ``[0, 1]``; MATLAB's default is 0.2.

    Returns
    -------
    (3, 3) ndarray of float64

    Examples
    --------
    >>> np.round(unsharp_kernel(0.2), 4)
    array([[-0.1667, -0.6667, -0.1667],
           [-0.6667,  4.3333, -0.6667],
           [-0.1667, -0.6667, -0.1667]])
    """
    alpha = float(alpha)
    if not 0.0 <= alpha <= 1.0:
        raise InputError(f"unsharp_alpha must lie in [0, 1], got {alpha}")
    a, b = -alpha, alpha - 1.0
    return np.array([[a, b, a], [b, alpha + 5.0, b], [a, b, a]]) / (alpha + 1.0)


def _median_stack(stack: np.ndarray, size: int) -> np.ndarray:
    # MATLAB medfilt2 pads with zeros; a depth-1 kernel never mixes slices. The median of
    # an all-zero neighbourhood is 0, so only the bounding box of the non-zero pixels
    # (plus the kernel's half width, where zero padding and zero pixels agree) is filtered.
    box = _nonzero_box(stack, size // 2)
    if box is None:
        return np.zeros_like(stack)
    out = np.zeros_like(stack)
    if size == 3:
        out[box] = _median3_in_plane(stack[box])
    else:
        out[box] = ndi.median_filter(stack[box], size=(1, size, size), mode="constant", cval=0)
    return out


def _med3(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Element-wise median of three arrays (exact: it returns one of the inputs)."""
    return np.maximum(np.minimum(a, b), np.minimum(np.maximum(a, b), c))


def _median3_in_plane(stack: np.ndarray) -> np.ndarray:
    """3 x 3 in-plane median of every slice, zero padding, without sorting.

    Equals ``ndi.median_filter(stack, size=(1, 3, 3), mode="constant", cval=0)``
    exactly: with each column of a 3 x 3 window sorted into ``lo <= mid <= hi``,
    the median of the nine values is ``med3(max(lo), med3(mid), min(hi))`` (the
    classic column-sort identity). Each vertical triple is sorted once and shared
    by the three windows that contain it; only min/max of the original values
    are taken, so any dtype gives the same result as the rank filter.
    """
    p = np.pad(stack, ((0, 0), (1, 1), (1, 1)))
    a, b, c = p[:, :-2], p[:, 1:-1], p[:, 2:]
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    lo3 = np.minimum(lo, c)
    t = np.maximum(lo, c)
    mid3 = np.minimum(hi, t)
    hi3 = np.maximum(hi, t)
    del a, b, c, lo, hi, t
    left, centre, right = slice(None, -2), slice(1, -1), slice(2, None)
    low = np.maximum(np.maximum(lo3[..., left], lo3[..., centre]), lo3[..., right])
    high = np.minimum(np.minimum(hi3[..., left], hi3[..., centre]), hi3[..., right])
    med = _med3(mid3[..., left], mid3[..., centre], mid3[..., right])
    return _med3(low, med, high)


def _nonzero_box(stack: np.ndarray, margin: int) -> tuple[slice, ...] | None:
    """In-plane bounding box of the non-zero pixels grown by ``margin`` (all slices)."""
    rows = np.flatnonzero(stack.any(axis=(0, 2)))
    cols = np.flatnonzero(stack.any(axis=(0, 1)))
    if rows.size == 0:
        return None
    ny, nx = stack.shape[1:]
    return (
        slice(None),
        slice(max(rows[0] - margin, 0), min(rows[-1] + margin + 1, ny)),
        slice(max(cols[0] - margin, 0), min(cols[-1] + margin + 1, nx)),
    )


def _unsharp_stack(stack: np.ndarray, alpha: float) -> np.ndarray:
    # MATLAB imfilter: correlation, zero padding, result rounded and saturated to uint8.
    # Outside the non-zero box grown by the kernel's half width every output is 0, and
    # inside it zero padding and zero pixels agree: only the box is filtered.
    kernel = unsharp_kernel(alpha)[None, :, :]
    out = np.zeros_like(stack, dtype=np.uint8)
    box = _nonzero_box(stack, 1)
    if box is None:
        return out
    acc = ndi.correlate(stack[box].astype(np.float64), kernel, mode="constant", cval=0.0)
    np.clip(acc, 0.0, 255.0, out=acc)
    acc += 0.5
    np.floor(acc, out=acc)
    out[box] = acc
    return out


def equalize_slices(stack: np.ndarray, *, levels: int = 256) -> np.ndarray:
    """Histogram-equalise each slice of an 8-bit stack independently [A2].

    Slice by slice, gray level ``g`` maps to
    ``T(g) = round((levels - 1) * cdf(g)) * 255 / (levels - 1)`` (rounded to
    uint8), where ``cdf`` is the cumulative histogram of the slice normalised
    to 1. With ``levels = 256`` this is ``skimage.exposure.equalize_hist``
    (which uses one bin per integer level) scaled to 0-255; ``levels = 64``
    mimics MATLAB's ``histeq`` default output resolution.

    Parameters
    ----------
    stack : (z, y, x) ndarray of uint8
    levels : int
        Number of output gray levels, 2-256.

    Returns
    -------
    (z, y, x) ndarray of uint8
    """
    stack = np.asarray(stack)
    if stack.ndim != 3 or stack.dtype != np.uint8:
        raise InputError("equalize_slices needs a 3-D uint8 (z, y, x) stack")
    if not 2 <= int(levels) <= 256:
        raise InputError(f"equalize_levels must lie in [2, 256], got {levels}")
    nz = stack.shape[0]
    flat = stack.reshape(nz, -1)
    # one 256-bin histogram per slice, without a Python loop over pixels
    offsets = (np.arange(nz, dtype=np.int64) * 256)[:, None]
    hist = np.bincount((flat + offsets).ravel(), minlength=256 * nz).reshape(nz, 256)
    cdf = np.cumsum(hist, axis=1) / flat.shape[1]
    top = levels - 1
    lut = np.floor(np.rint(cdf * top) * (255.0 / top) + 0.5).astype(np.uint8)
    return np.take_along_axis(lut, flat.astype(np.intp), axis=1).reshape(stack.shape)
