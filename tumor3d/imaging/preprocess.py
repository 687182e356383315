"""Preprocessing of a stack of MR slices (specification section 1).

Per 8-bit slice ``I`` (Arakeri & Reddy 2013, section 3.1):

1. ``I1`` = 3x3 median filter of ``I``;
2. ``I2`` = clip(``I1`` (*) h, 0, 255) with ``h`` MATLAB's
   ``fspecial('unsharp', alpha)`` kernel [A1];
3. ``I3`` = histogram equalisation of ``I2`` with 256 levels [A2];
4. ``M_brain`` = skull removal on the *original* ``I``: Otsu threshold,
   opening with a disk, largest 8-connected component, dilation with the same
   disk, hole filling [A3]; ``J = I3 * M_brain``.

Steps 2 and 3 are implemented but **off by default** (``sharpen=False``,
``equalize=False``) and off in ``configs/paper.yaml`` too: equalisation
flattens the very histogram whose modes section 2 counts, and the unsharp
kernel's overshoot saturates at the gray of CSF and turns noise and tissue
edges into extra modes. :func:`preprocess_volume` gives the measurements
behind this choice (and ``reports/PAPER.md``, ``make paper``, the figures of
every reading tried).

The volume is processed as a stack: the median filter and the unsharp
kernel are applied to the whole ``(z, y, x)`` array with a kernel of depth 1
(so slices never mix), the equalisation is one table look-up per slice, the
morphology (erosion, labelling, dilation, hole filling) runs on the whole
stack with in-plane structuring elements, and only the skull removal's Otsu
thresholds are computed slice by slice.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
from scipy import ndimage as ndi
from skimage.filters import threshold_multiotsu, threshold_otsu
from skimage.morphology import disk

from tumor3d.errors import InputError
from tumor3d.imaging.brain_extraction import extract_brain, head_around_brain, head_exterior

__all__ = [
    "MaskedBackground",
    "PreprocessResult",
    "equalize_slices",
    "foreground_brain_mask",
    "masked_background",
    "preprocess_volume",
    "remove_skull",
    "to_uint8",
    "unsharp_kernel",
]


@dataclass(frozen=True, eq=False)
class PreprocessResult:
    """Output of :func:`preprocess_volume`; all arrays are ``(z, y, x)``.

    Attributes
    ----------
    original_u8 : ndarray of uint8
        ``I``: the 8-bit slices the method starts from.
    enhanced : ndarray of uint8
        ``J = I3 * M_brain``: median filtered (and, if enabled, sharpened and
        equalised), with everything outside the brain set to 0.
    brain_mask : ndarray of bool
        ``M_brain``: the brain after skull removal (empty on slices without
        tissue).
    brain_extraction : str
        How ``M_brain`` was found: ``"given"`` (``brain_mask``),
        ``"foreground"``, ``"skull_strip"`` or ``"head"`` (the
        ``brain_extraction`` used, ``auto`` resolved).
    head_exterior : ndarray of bool or None
        Where the brain was found inside a raw head (``"skull_strip"``,
        ``"head"``) and the volume shows a head around it
        (:func:`tumor3d.imaging.brain_extraction.head_around_brain`): the air outside
        the head (:func:`tumor3d.imaging.brain_extraction.head_exterior`), which no
        brain voxel comes within the scalp and skull's thickness of. None for a
        skull-stripped volume (``"foreground"``), a given mask, and a volume
        of the brain alone.
    """

    original_u8: np.ndarray
    enhanced: np.ndarray
    brain_mask: np.ndarray
    brain_extraction: str = ""
    head_exterior: np.ndarray | None = None


# --------------------------------------------------------------------------- validation


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


# --------------------------------------------------------------------------- 8-bit conversion


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


# --------------------------------------------------------------------------- filters


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


# --------------------------------------------------------------------------- skull removal

SKULL_THRESHOLDS = ("otsu", "multiotsu")


def _skull_threshold(sl: np.ndarray, method: str) -> float:
    if method == "multiotsu" and np.unique(sl).size >= 3:
        return float(threshold_multiotsu(sl, classes=3)[0])
    return float(threshold_otsu(sl))


def remove_skull(
    original_u8: np.ndarray, *, opening_radius: int = 2, threshold: str = "multiotsu"
) -> np.ndarray:
    """Brain mask ``M_brain`` of every slice from the original 8-bit image [A3].

    Per slice:

    1. ``B = I > t``, ``t`` the Otsu threshold of the slice (see below);
    2. erode ``B`` with a disk of radius ``opening_radius``: this cuts the
       thin bridges between scalp and brain;
    3. keep the largest 8-connected component;
    4. dilate it with the same disk (steps 2-4 are the opening of the
       specification, with the component selection between its erosion and
       its dilation);
    5. fill its holes (ventricles, dark necrosis).

    A slice whose gray levels are all equal (no tissue), or where nothing
    survives the erosion, gets an empty mask.

    Deviations from the literal [A3] recipe ("opening, largest component,
    dilation"), each a documented choice:

    - Near the top and bottom of the head the scalp (a ring, or a solid disc
      where the slice cuts it tangentially) is larger than the brain's
      cross-section and becomes "the largest component"; hole-filled, it is
      a disc of scalp, skull and brain whose histogram has spurious modes
      (measured on the phantoms: false abnormal slices with up to 8770 px of
      scalp segmented as tumour). Brain cross-sections shrink from the
      widest slice outwards, so, walking outwards, a slice whose mask lies
      mostly outside its inner neighbour's is past the brain: it and the
      slices beyond are cleared (:func:`_keep_nested_slices`; when that walk
      keeps fewer slices than it clears, it started on a face or neck slice
      wider than the brain and is walked again from the widest slice it
      cleared). This loses
      the brain's extreme end slices where the scalp outsizes them. No
      per-slice rule can tell a scalp ring around the brain from a brain rim
      around a tumour (plain Otsu on T2): they are the same topology.

    - Applying a full opening and *then* another dilation would grow the
      mask by ``opening_radius`` pixels into the dark skull, adding a
      spurious dark population to the brain histogram of section 2. Taking
      the component between the erosion and the dilation cuts the same
      bridges and leaves the brain border where the threshold put it.
    - ``threshold="multiotsu"`` (default) uses the lower of the two 3-class
      Otsu thresholds instead of the 2-class Otsu threshold
      (``threshold="otsu"``). On T2 slices the 2-class threshold often
      separates bright CSF/lesion from darker white matter instead of tissue
      from air and bone, and the brain falls apart into pieces (observed on
      BraTS T2 and a DIPY T2 volume); the lower 3-class threshold separates
      air/bone from all soft tissue. On raw heads both give the same mask.

    Parameters
    ----------
    original_u8 : (z, y, x) ndarray of uint8
        ``I``, the unfiltered slices.
    opening_radius : int
        Disk radius in pixels; 0 skips the erosion and the dilation.
    threshold : {"multiotsu", "otsu"}
        Which Otsu threshold to binarise with.

    Returns
    -------
    (z, y, x) ndarray of bool
    """
    stack = np.asarray(original_u8)
    if stack.ndim != 3 or stack.dtype != np.uint8:
        raise InputError("remove_skull needs a 3-D uint8 (z, y, x) stack")
    radius = int(opening_radius)
    if radius < 0:
        raise InputError(f"skull_opening_radius must be >= 0, got {opening_radius}")
    if threshold not in SKULL_THRESHOLDS:
        raise InputError(
            f"unknown skull_threshold {threshold!r}: expected one of {SKULL_THRESHOLDS}"
        )
    binary = np.zeros(stack.shape, dtype=bool)
    for z, sl in enumerate(stack):
        if sl.min() != sl.max():
            binary[z] = sl > _skull_threshold(sl, threshold)
    mask = _opened_largest_component(binary, radius)
    return _keep_nested_slices(fill_holes_per_slice(mask))


def _in_plane(footprint: np.ndarray) -> np.ndarray:
    """A 2-D footprint as a ``(1, h, w)`` structure: it never links slices."""
    return np.asarray(footprint, dtype=bool)[None]


def _opened_largest_component(binary: np.ndarray, radius: int) -> np.ndarray:
    """Per slice: erode by a disk, keep the largest 8-connected component, dilate.

    All slices in a few whole-stack calls, on the bounding box of ``binary``
    grown by ``radius`` (outside it every input pixel, hence every output
    pixel, is False; scipy's border value is False as well). A depth-1
    structure never mixes slices. The labels of a 3-D labelling with an
    in-plane structure run slice by slice in raster order, so each slice's
    labels are one consecutive range and the first largest component of that
    range is the one a per-slice ``argmax`` picks.
    """
    out = np.zeros(binary.shape, dtype=bool)
    box = _true_box(binary)
    if box is None:
        return out
    ny, nx = binary.shape[1:]
    box = (
        box[0],
        slice(max(box[1].start - radius, 0), min(box[1].stop + radius, ny)),
        slice(max(box[2].start - radius, 0), min(box[2].stop + radius, nx)),
    )
    sub = binary[box]
    footprint = _in_plane(disk(radius)) if radius > 0 else None
    if footprint is not None:
        sub = ndi.binary_erosion(sub, structure=footprint)
    eight = np.zeros((3, 3, 3), dtype=bool)
    eight[1] = True
    labels, n = ndi.label(sub, structure=eight)
    if n == 0:
        return out
    sizes = np.bincount(labels.ravel())
    top = labels.reshape(len(labels), -1).max(axis=1)  # last label of each slice (0: none)
    keep = np.zeros(n + 1, dtype=bool)
    first = 1
    for last in top:
        if last >= first:
            keep[first + int(np.argmax(sizes[first : last + 1]))] = True
            first = last + 1
    brain = keep[labels]
    if footprint is not None:
        brain = ndi.binary_dilation(brain, structure=footprint)
    out[box] = brain
    return out


#: Towards the top and bottom of the head a slice's brain must lie within its
#: inner neighbour's brain dilated by this many pixels, up to this fraction.
_NESTING_TOLERANCE_PX = 3
_NESTING_MAX_OUTSIDE = 0.2


def _keep_nested_slices(mask: np.ndarray) -> np.ndarray:
    """Clear the slices beyond the brain's extent at both ends of the stack.

    Cross-sections of the brain shrink from its widest slice outwards. Walking
    outwards from the slice of largest mask area, a slice whose mask lies
    more than ``_NESTING_MAX_OUTSIDE`` outside its inner neighbour's mask
    (dilated by ``_NESTING_TOLERANCE_PX``) is past the brain, where the
    slice cuts scalp or skull tangentially into a solid disc: it and every
    slice beyond it are cleared.

    The largest mask is not the brain's when a scan reaches below the skull
    base: a slice through the face or the neck can be wider than any slice
    of the brain, and the walk from it clears the brain itself (a raw TCGA
    head: every slice but the three lowest). So when the walk keeps fewer
    slices with a mask than it clears, it is walked again from the largest
    cleared slice, and the walk that keeps more slices is taken. A scalp
    disc or a face slice at the end of a head is a slice or two, never most
    of the stack, so the walk from the brain's widest slice keeps its result.
    A scan holding more face and neck slices than brain slices is beyond this
    rule (the run's notes then say the mask lies on few slices only if it is
    under half of them: :func:`brain_coverage_note`).
    """
    areas = mask.sum(axis=(1, 2))
    if not areas.any():
        return mask
    # The walk never changes a slice's inner neighbour (it only decides where to stop),
    # so all the dilations are done in one call.
    r = _NESTING_TOLERANCE_PX
    dilated = np.zeros_like(mask)
    box = _true_box(mask)
    ny, nx = mask.shape[1:]
    box = (
        slice(None),
        slice(max(box[1].start - r, 0), min(box[1].stop + r, ny)),
        slice(max(box[2].start - r, 0), min(box[2].stop + r, nx)),
    )
    dilated[box] = ndi.binary_dilation(mask[box], structure=_in_plane(disk(r)))
    has = areas > 0

    def walk(centre: int) -> tuple[int, int]:
        """The first and last slice kept walking outwards from ``centre``."""
        ends = []
        for step in (-1, 1):
            z = centre + step
            while 0 <= z < len(mask):
                outside = np.count_nonzero(mask[z] & ~dilated[z - step])
                if outside > _NESTING_MAX_OUTSIDE * max(1, int(areas[z])):
                    break
                z += step
            ends.append(z - step)
        return ends[0], ends[1]

    lo, hi = walk(int(np.argmax(areas)))
    kept = int(np.count_nonzero(has[lo : hi + 1]))
    if int(np.count_nonzero(has)) - kept > kept:
        # the widest slice is not the brain's (a face or neck slice): walk again from
        # the widest slice it cleared
        cleared = has.copy()
        cleared[lo : hi + 1] = False
        lo2, hi2 = walk(int(np.argmax(np.where(cleared, areas, -1))))
        if int(np.count_nonzero(has[lo2 : hi2 + 1])) > kept:
            lo, hi = lo2, hi2
    out = mask.copy()
    out[:lo] = False
    out[hi + 1 :] = False
    return out


# --------------------------------------------------------------------------- skull-stripped input

BRAIN_EXTRACTIONS = ("auto", "skull_strip", "foreground", "head")

#: No brain mask can hold more than this (mL): the intracranial volume of adults
#: (brain, CSF and meninges together) lies between about 1.1 and 1.9 L. A larger
#: mask holds scalp, face or neck (measured: 2.6-3.3 L on the raw clinical heads of
#: ``../shared/data``, where the per-slice skull removal keeps the scalp).
MAX_INTRACRANIAL_ML = 2000.0


def brain_volume_note(brain_volume_ml: float) -> str | None:
    """A warning for a brain mask that holds more than any skull can, else None.

    Such a mask holds scalp, face or neck, where the lesion model may find a
    "lesion" (fat, muscle, sinus), and its statistics of normal tissue are off; the
    result, a tumour volume or "no tumour found", is then not to be trusted.

    >>> brain_volume_note(1400.0) is None
    True
    >>> brain_volume_note(3257.0)[:40]
    'brain mask of 3257 mL: more than any sku'
    """
    v = float(brain_volume_ml)
    if not v > MAX_INTRACRANIAL_ML:
        return None
    return (
        f"brain mask of {v:.0f} mL: more than any skull holds ({MAX_INTRACRANIAL_ML:.0f} mL), "
        "so it holds scalp or face and the result (a tumour volume, or no tumour found) is not "
        "reliable: give the brain mask (--brain-mask) or set preprocess.brain_extraction: "
        "head, and check overlay_brain.png"
    )


#: No whole human brain shows less than this (mm2) on its largest slice: a brain's
#: largest cross-section (axial, coronal or sagittal) is about 60 cm2 at birth and
#: 100-250 cm2 in adults (measured: 142-258 cm2 on the real volumes and phantoms the
#: project uses). Below a third of the newborn's, the voxel size in the header is off
#: (a unit error: 0.1 mm read for 1 mm pixels makes the area 100 times smaller) or
#: the brain was lost.
MIN_BRAIN_SLICE_MM2 = 2000.0


def brain_size_note(largest_slice_mm2: float) -> str | None:
    """A warning for a brain mask too small to be a human brain, else None.

    ``largest_slice_mm2`` is the brain mask's area on its largest slice
    (through the scan's pixel spacing): see :data:`MIN_BRAIN_SLICE_MM2`.

    >>> brain_size_note(15000.0) is None
    True
    >>> brain_size_note(150.0)[:44]
    'brain mask of at most 1.5 cm2 on any slice: '
    """
    a = float(largest_slice_mm2)
    if not a < MIN_BRAIN_SLICE_MM2:
        return None
    return (
        f"brain mask of at most {a / 100.0:.1f} cm2 on any slice: no human brain is that small "
        f"(its largest cross-section is about 60 cm2 at birth, 100-250 cm2 in adults), so the "
        "voxel size in the image header is likely wrong (a unit error, e.g. 0.1 mm pixels "
        "for 1 mm) or the brain was lost, and every volume is not reliable: check the "
        "header's voxel size and overlay_brain.png"
    )


#: A brain mask on fewer than this share of the slices that hold tissue has lost most
#: of the brain: the brain spans most of a head scan's slices (the phantoms' whole
#: heads: 63-73 %, 59 % with ``brain_extraction: head``; the raw clinical heads of
#: ``../shared/data``: 65-100 %; skull-stripped volumes: 100 %), while a skull removal
#: misled by a face or neck slice kept 3 of 26.
MIN_BRAIN_SLICE_SHARE = 0.5


def tissue_slice_count(original_u8: np.ndarray) -> int:
    """Slices of a ``(z, y, x)`` stack that hold anything: not one constant gray.

    A skull-stripped volume's slices beyond the brain are its constant background;
    a raw head's slices hold head, or at least the scanner's noise.

    >>> tissue_slice_count(np.stack([np.zeros((4, 4)), np.eye(4)]).astype(np.uint8))
    1
    """
    flat = np.asarray(original_u8).reshape(len(original_u8), -1)
    if flat.size == 0:
        return 0
    return int(np.count_nonzero(flat.max(axis=1) > flat.min(axis=1)))


def brain_coverage_note(
    brain_slices: int, tissue_slices: int, brain_extraction: str = ""
) -> str | None:
    """A warning for a brain mask on too few of the slices that hold tissue, else None.

    Below :data:`MIN_BRAIN_SLICE_SHARE`, the skull removal has most likely lost
    the brain (a face or neck slice taken for the brain's widest, or the scalp
    joined to the brain on a slice), and what it kept may be face or neck.
    ``brain_extraction`` (the mode used) keeps the advice from naming the mode
    that failed.

    >>> brain_coverage_note(20, 30) is None
    True
    >>> brain_coverage_note(3, 26)[:48]
    'brain mask on 3 of the 26 slices that hold tissu'
    """
    b, t = int(brain_slices), int(tissue_slices)
    if t <= 0 or b >= MIN_BRAIN_SLICE_SHARE * t:
        return None
    advice = "give the brain mask (--brain-mask)"
    if brain_extraction != "head":
        advice += " or set preprocess.brain_extraction: head"
    return (
        f"brain mask on {b} of the {t} slices that hold tissue: the skull removal has likely "
        "lost most of the brain (or kept face or neck), so the result (a tumour volume, or no "
        f"tumour found) is not reliable: {advice}, and check overlay_brain.png"
    )


def foreground_brain_mask(image: np.ndarray) -> np.ndarray:
    """Brain mask of an already skull-stripped volume: its foreground.

    Foreground = voxels that differ from the constant masked background
    (:func:`masked_background`, whatever its value: 0, negative for z-scored
    volumes, or 0 below a brain with negative values too); the largest
    26-connected 3-D component is kept (stray background specks drop out)
    and each slice's holes are filled (dark necrosis or ventricles whose
    intensity equals the background). Nothing is eroded, so the brain's rim,
    where a tumour may touch the surface, stays in.

    Parameters
    ----------
    image : (z, y, x) ndarray of real numbers

    Returns
    -------
    (z, y, x) ndarray of bool
        Empty if the volume is constant.
    """
    return _foreground_brain_mask(_check_volume(image))


def _foreground_brain_mask(arr: np.ndarray, background=None) -> np.ndarray:
    bg = masked_background(arr) if background is None else background
    fg = ~bg.mask
    box = _true_box(fg)
    if box is None:
        return fg
    # Components, their sizes and their raster order (argmax's tie-break) are the same
    # on the bounding box of the foreground as on the whole volume.
    sub = fg[box]
    labels, n = ndi.label(sub, structure=np.ones((3, 3, 3), dtype=bool))
    if n > 1:
        sizes = np.bincount(labels.ravel())
        sizes[0] = 0
        sub = labels == int(np.argmax(sizes))
        # the largest component may have a smaller box: hole filling works on that one
        fg = np.zeros_like(fg)
        fg[box] = sub
    return fill_holes_per_slice(fg)


def _true_box(mask: np.ndarray) -> tuple[slice, ...] | None:
    """Bounding box (all three axes) of the True voxels of a 3-D mask, or None."""
    zs = np.flatnonzero(mask.any(axis=(1, 2)))
    if zs.size == 0:
        return None
    ys = np.flatnonzero(mask.any(axis=(0, 2)))
    xs = np.flatnonzero(mask.any(axis=(0, 1)))
    return (
        slice(zs[0], zs[-1] + 1),
        slice(ys[0], ys[-1] + 1),
        slice(xs[0], xs[-1] + 1),
    )


#: 4-connectivity in the (y, x) plane and no link between slices.
_IN_PLANE_4 = np.zeros((3, 3, 3), dtype=bool)
_IN_PLANE_4[1] = ndi.generate_binary_structure(2, 1)


def fill_holes_per_slice(mask: np.ndarray) -> np.ndarray:
    """Fill the holes of every ``(y, x)`` slice of a ``(z, y, x)`` mask in one call.

    Same result as ``scipy.ndimage.binary_fill_holes`` of each slice (holes =
    background pixels not 4-connected to the slice border). The background of
    the mask's bounding box, framed by a one-pixel ring of background that
    stands for everything outside the box (background on every slice, hence
    connected to the border), is labelled once with a structuring element
    that links 4-neighbours within a slice and never across slices; every
    background component other than the ring's own is a hole.

    Examples
    --------
    >>> ring = np.ones((1, 5, 5), dtype=bool); ring[0, 2, 2] = False
    >>> bool(fill_holes_per_slice(ring)[0, 2, 2])
    True
    """
    mask = np.asarray(mask, dtype=bool)
    if mask.ndim != 3:
        raise InputError("fill_holes_per_slice needs a 3-D (z, y, x) mask")
    out = mask.copy()
    box = _true_box(mask)
    if box is None:
        return out
    background = np.pad(~mask[box], ((0, 0), (1, 1), (1, 1)), constant_values=True)
    labels, _ = ndi.label(background, structure=_IN_PLANE_4)
    outside = labels[:, :1, :1]  # the ring's component, one per slice
    holes = labels[:, 1:-1, 1:-1]
    out[box] |= (holes != outside) & (holes > 0)
    return out


# --------------------------------------------------------------------------- pipeline


def preprocess_volume(
    image: np.ndarray,
    *,
    window_percentiles=(0.5, 99.5),
    median_size: int = 3,
    sharpen: bool = False,
    unsharp_alpha: float = 0.2,
    equalize: bool = False,
    equalize_levels: int = 256,
    skull_threshold: str = "multiotsu",
    skull_opening_radius: int = 2,
    brain_extraction: str = "auto",
    masked_background_fraction: float = 0.3,
    brain_mask: np.ndarray | None = None,
    spacing_mm: tuple[float, float, float] | None = None,
) -> PreprocessResult:
    """Run section 1 of the specification on a stack of slices.

    ``I`` is ``image`` itself when it is already uint8 (the paper's 8-bit
    slices are used as they are), otherwise :func:`to_uint8` of it. Then

    - ``I1 = median(I)``, ``median_size`` x ``median_size``, zero padding
      (MATLAB ``medfilt2``), as a ``(1, s, s)`` filter over the stack;
    - ``I2 = clip(round(I1 (*) h), 0, 255)``, ``h`` = :func:`unsharp_kernel`
      of ``unsharp_alpha`` [A1], zero padding (MATLAB ``imfilter``), if
      ``sharpen``; otherwise ``I2 = I1``;
    - ``I3`` = :func:`equalize_slices` of ``I2`` with ``equalize_levels``
      levels [A2], if ``equalize``; otherwise ``I3 = I2``;
    - ``M_brain`` = :func:`remove_skull` of ``I`` [A3], or the image's own
      foreground when it is already skull-stripped (``brain_extraction``,
      see :func:`foreground_brain_mask`), or ``brain_mask`` when given;
    - ``J = I3 * M_brain``.

    Why ``sharpen`` and ``equalize`` are off by default and in
    ``configs/paper.yaml`` (deviation from the paper's steps 2-3, measured on
    the T2 phantoms seeds 0-7 and tumour-free 0-3 of ``reports/PAPER.md``):

    - Histogram equalisation maps each gray level to its cumulative
      frequency ``T = cdf``, so the equalised histogram is flat by
      construction (output density ``p / T' = 1``): its modes, which
      section 2 counts and section 3 clusters, are spread into a uniform
      band. Over the whole slice (the literal reading [A2]) the air and
      scalp take most of the levels and the brain is squeezed into 180-255
      (demo phantom, slice 15: WM 206, GM 230, tumour 242, CSF 255); the FCM
      then finds no tumour cluster on any slice (the paper configuration
      with ``equalize=True``, 256 or 64 levels: 0 of 64 tumour slices
      segmented). No reading restores the modes: brain only, whole volume,
      256 or 64 levels, before or after sharpening, Otsu or multi-Otsu skull
      mask, the full-resolution or the Haar ``LL`` histogram: at best 42 of
      64 tumour slices flagged with 4 normal slices flagged, or all 64 with
      125 or more of 185 normal slices flagged.
    - The unsharp kernel (centre weight ``(alpha+5)/(alpha+1) = 4.33``)
      amplifies noise about 4.5-fold and creates over/undershoots at every
      tissue edge, clipped into spikes at 0 and 255; these become extra
      histogram modes. At a bright tumour's edge the overshoot saturates at
      255, the gray of CSF on T2, and the FCM labels the tumour's inner rim
      CSF (demo slice 15: 103 of 972 tumour pixels lost, grays 190-255): the
      paper configuration with ``sharpen=True`` loses 10 % of the tumour
      pixels on average (Eq. 9), 14 % at worst.

    Both steps remain available (``sharpen=True, equalize=True`` is the
    paper's literal chain).

    Parameters
    ----------
    image : (z, y, x) ndarray of real numbers
        The slices, ``z`` the slice axis. Not modified.
    window_percentiles : (float, float)
        Foreground percentiles of the 8-bit window (ignored for uint8 input).
    median_size : int
        Odd median filter size in pixels.
    sharpen : bool
        Apply the unsharp kernel (paper step 2).
    unsharp_alpha : float
        ``alpha`` of ``fspecial('unsharp')``, in ``[0, 1]``.
    equalize : bool
        Apply per-slice histogram equalisation (paper step 3).
    equalize_levels : int
        Gray levels of the equalised image, 2-256.
    skull_threshold : {"multiotsu", "otsu"}
        Threshold of the skull removal, see :func:`remove_skull`.
    skull_opening_radius : int
        Radius (pixels) of the disk of the skull removal's opening.
    brain_extraction : {"auto", "skull_strip", "foreground", "head"}
        ``skull_strip``: :func:`remove_skull` (the paper's step 4);
        ``foreground``: :func:`foreground_brain_mask` (the volume is already
        skull-stripped: keep the whole brain, no rim eaten); ``head``:
        :func:`tumor3d.imaging.brain_extraction.extract_brain`, a 3-D extraction in mm
        for raw clinical heads where the per-slice skull removal keeps the
        scalp (measured on the raw heads of ``../shared/data``: 1.2-1.5 L
        brains instead of 2.6-3.3 L heads; not the default, because on the
        phantoms, where the skull removal succeeds, it loses the end slices
        and a 1-2 mm rim, and because the lesion model then reported false
        lesions in normal white matter on two raw T1 heads, see
        ``reports/segmentation.md``; needs ``spacing_mm``); ``auto``:
        ``foreground`` when at least ``masked_background_fraction`` of the
        voxels hold the masked background value (:func:`masked_background`:
        the volume's minimum or the border's most frequent value, up to the
        rounding of a resampling), else ``skull_strip``.
        Reason: the air of a raw magnitude MR volume carries Rician noise,
        so a large set of voxels sharing one exact value is a mask applied
        by skull stripping (0 in BraTS T2, the z-scored background -3.16 of
        the BraTS FLAIR cases). Measured: 81-89 % on the BraTS volumes,
        2-6 % on the raw clinical volumes of ``../shared/data``.
    masked_background_fraction : float
        Threshold of the ``auto`` rule, in (0, 1].
    brain_mask : (z, y, x) array_like of bool, optional
        A known brain mask (e.g. BraTS ``brainmask``); replaces the skull
        removal. Not a configuration parameter.
    spacing_mm : (3,) tuple of float, optional
        Voxel spacing ``(slice step, row, column)`` in mm; needed by
        ``brain_extraction="head"``. Not a configuration parameter (the stage
        adapter passes the scan's).

    Returns
    -------
    PreprocessResult

    Raises
    ------
    InputError
        For a non-3-D, non-real, NaN-containing or constant ``image``, a
        ``brain_mask`` of another shape, or an out-of-range parameter.

    References
    ----------
    R. Arakeri, G. R. M. Reddy, "3D reconstruction of brain tumor and volume
    estimation from MR images", IJSIP 6(3), 2013, section 3.1.
    """
    arr = _check_volume(image)
    lo_p, hi_p = _check_percentiles(window_percentiles)
    size = int(median_size)
    if size < 1 or size % 2 == 0:
        raise InputError(f"median_size must be a positive odd integer, got {median_size}")
    if not 0.0 <= float(unsharp_alpha) <= 1.0:
        raise InputError(f"unsharp_alpha must lie in [0, 1], got {unsharp_alpha}")
    if not 2 <= int(equalize_levels) <= 256:
        raise InputError(f"equalize_levels must lie in [2, 256], got {equalize_levels}")
    if brain_mask is not None:
        given = np.asarray(brain_mask)
        if given.shape != arr.shape:
            raise InputError(
                f"brain_mask shape {given.shape} does not match image shape {arr.shape}"
            )
        given = given.astype(bool)
    if arr.dtype == np.uint8:
        if arr.min() == arr.max():
            raise InputError("image is constant: there is no tissue to process")
        original = arr.copy()
        background = None
    else:
        background = masked_background(arr)  # computed once: the window, auto, foreground
        original = _to_uint8(arr, lo_p, hi_p, background)
    enhanced = _median_stack(original, size)
    if sharpen:
        enhanced = _unsharp_stack(enhanced, unsharp_alpha)
    if equalize:
        enhanced = equalize_slices(enhanced, levels=equalize_levels)
    if brain_extraction not in BRAIN_EXTRACTIONS:
        raise InputError(
            f"unknown brain_extraction {brain_extraction!r}: expected one of {BRAIN_EXTRACTIONS}"
        )
    if not 0.0 < float(masked_background_fraction) <= 1.0:
        raise InputError(
            f"masked_background_fraction must lie in (0, 1], got {masked_background_fraction}"
        )
    mode = brain_extraction
    if mode == "auto":
        share = (masked_background(arr) if background is None else background).share
        mode = "foreground" if share >= float(masked_background_fraction) else "skull_strip"
    if spacing_mm is not None:
        sp = tuple(float(v) for v in np.ravel(spacing_mm))
        if len(sp) != 3 or not all(np.isfinite(v) and v > 0 for v in sp):
            raise InputError(f"spacing_mm must be three positive numbers, got {spacing_mm}")
    if brain_mask is not None:
        brain = given
        mode = "given"
    elif mode == "foreground":
        brain = _foreground_brain_mask(arr, background)
    elif mode == "head":
        if spacing_mm is None:
            raise InputError("brain_extraction 'head' needs the voxel spacing (spacing_mm)")
        brain = extract_brain(original, sp)
    else:
        brain = remove_skull(
            original, opening_radius=skull_opening_radius, threshold=skull_threshold
        )

    enhanced = np.where(brain, enhanced, np.uint8(0))
    exterior = None
    if mode in ("skull_strip", "head"):  # a raw head: its air, if it shows a head at all
        pixel_mm = (1.0, 1.0) if spacing_mm is None else (sp[1], sp[2])
        exterior = head_exterior(original, pixel_mm)
        if not head_around_brain(brain, exterior, pixel_mm):
            exterior = None
    return PreprocessResult(
        original_u8=original, enhanced=enhanced, brain_mask=brain, brain_extraction=mode,
        head_exterior=exterior,
    )  # fmt: skip
