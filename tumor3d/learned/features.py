"""Per-pixel features of the learned lesion model: intensity, context, symmetry, position.

The features are 2-D (in-plane) with one neighbour-slice term, so that they
mean the same on thick clinical slices (5-7 mm) as on 1 mm volumes, in the
spirit of the BraTS 2013 forests (Zikic et al. 2012; Tustison et al. 2015,
doi:10.1007/s12021-014-9245-2): multi-scale smoothed intensity, local
spread, left-right asymmetry, depth below the tissue's surface, and
position. Every length is in mm (``spacing_mm``), every intensity is
normalised per patient by the median and robust spread of the tissue deeper
than the scalp and skull (:func:`normalise_intensity`), so a z-scored BraTS
brain, an 8-bit clinical head and a uint16 scanner export give the same
features, and no brain extraction (which fails on many raw heads) is needed.

Arrays are ``(z, y, x)``, ``z`` the slice axis. Nothing here reads a file.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage as ndi

from tumor3d.errors import InputError
from tumor3d.imaging.preprocess import fill_holes_per_slice, true_box

__all__ = [
    "FEATURE_NAMES",
    "MODALITY_CODES",
    "PatientFeatures",
    "compute_features",
    "normalise_intensity",
    "tissue_foreground",
]

#: Modality code of the ``modality`` feature (one model serves FLAIR and T2).
MODALITY_CODES: dict[str, float] = {"flair": 0.0, "t2": 1.0, "t1c": 2.0}

#: In-plane Gaussian scales (mm) of the smoothed intensity.
_SMOOTH_MM = (1.0, 2.0, 4.0, 8.0, 16.0)

FEATURE_NAMES: tuple[str, ...] = (
    "intensity",
    *(f"smooth_{s:g}mm" for s in _SMOOTH_MM),
    "local_sd_2mm",
    "local_sd_4mm",
    "mirror_diff_2mm",
    "mirror_diff_4mm",
    "mirror_diff_8mm",
    "neighbour_slices_2mm",
    "log_4mm",
    "slice_excess_2mm",
    "slice_p99",
    "patient_p99",
    "depth_mm",
    "relative_depth",
    "lr_offset",
    "ap_position",
    "z_position",
    "slice_tissue_area",
    "modality",
    "prior_inside",
    "prior_distance_mm",
    "prior_slice_area",
)

#: Clip (mm) of the signed in-plane distance to the prior's boundary.
PRIOR_DISTANCE_CLIP_MM = 30.0


@dataclass(frozen=True)
class PatientFeatures:
    """The features of one patient's candidate pixels.

    Attributes
    ----------
    values : (n, len(FEATURE_NAMES)) ndarray of float32
        One row per candidate pixel, columns :data:`FEATURE_NAMES`.
    index : (n,) ndarray of int64
        Flat index of each row's pixel in the ``(z, y, x)`` volume.
    shape : tuple of int
        The volume's shape.
    candidates : (z, y, x) ndarray of bool
        The pixels that have a row (the head's or brain's tissue).
    """

    values: np.ndarray
    index: np.ndarray
    shape: tuple[int, int, int]
    candidates: np.ndarray


def _check_image(image: object) -> np.ndarray:
    img = np.asarray(image)
    if img.ndim != 3 or img.size == 0:
        raise InputError(f"image must be a non-empty 3-D (z, y, x) array, got shape {img.shape}")
    if not np.issubdtype(img.dtype, np.number) or np.iscomplexobj(img):
        raise InputError(f"image must hold real numbers, got dtype {img.dtype}")
    img = img.astype(np.float32)
    if not np.all(np.isfinite(img)):
        raise InputError("image holds NaN or infinite values")
    return img


def tissue_foreground(image: np.ndarray) -> np.ndarray:
    """The tissue of the volume (a head, or a brain alone), holes filled per slice.

    Tissue is brighter than the lower of the volume's two 3-class Otsu
    thresholds (air and bone below it, soft tissue above; on a skull-stripped
    volume the masked background below), opened by a 3 x 3 square in-plane
    to drop noise specks, its largest 3-D component, holes filled per slice
    (skull, sinuses and CSF inside the head count as tissue). No brain mask
    is used: a brain extraction that fails on a raw head (it does on many of
    the clinical heads of ``../shared/data``) cannot move the features.

    The thresholds are those of the histogram (256 bins from the volume's lowest
    value) of every voxel in the box of the voxels above the lowest value
    (:func:`tumor3d.imaging.preprocess.true_box`): rows, columns and slices of that
    value around the head (an exporter's padding, a wider field of view) leave the mask
    as it is. Noisy air, above the lowest value, is inside that box and moves it.

    Examples
    --------
    >>> img = np.zeros((2, 20, 20)); img[:, 4:16, 4:16] = 100.0; img[:, 8:12, 8:12] = 5.0
    >>> int(tissue_foreground(img).sum())
    288
    """
    from skimage.filters import threshold_multiotsu

    img = _check_image(image)
    low = float(img.min())
    content = true_box(img > low)
    box = img if content is None else img[content]
    counts, edges = np.histogram(box, bins=256, range=(low, max(float(box.max()), low + 1e-6)))
    try:
        centres = 0.5 * (edges[1:] + edges[:-1])
        level = float(threshold_multiotsu(hist=(counts, centres), classes=3)[0])
    except ValueError:  # fewer than three gray levels
        level = low
    tissue = ndi.binary_opening(img > level, structure=np.ones((1, 3, 3), bool))
    labels, n = ndi.label(tissue)
    if n == 0:
        return tissue
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return fill_holes_per_slice(labels == int(np.argmax(sizes)))


#: Depth (mm) below the tissue's surface beyond which a head holds brain only (the
#: scalp and skull together are 5-12 mm thick): the intensity reference region.
REFERENCE_DEPTH_MM = 20.0


def normalise_intensity(image: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """``(I - median) / spread`` over ``reference``; spread = IQR / 1.349 (a robust SD).

    A reference without spread (a constant region) uses 1; an empty one, the
    whole image.

    Examples
    --------
    The median (3.5) maps to 0 and one robust SD (IQR 3.5 / 1.349) to 1, so
    the darkest voxel lies -1.349 robust SDs below:

    >>> img = np.arange(8, dtype=float).reshape(2, 2, 2)
    >>> round(float(normalise_intensity(img, np.ones_like(img, bool))[0, 0, 0]), 3)
    -1.349
    """
    img = _check_image(image)
    ref = np.asarray(reference, dtype=bool)
    vals = img[ref] if ref.any() else img.ravel()
    q25, med, q75 = np.percentile(vals, [25.0, 50.0, 75.0])
    spread = float(q75 - q25) / 1.349
    if not spread > 0:
        spread = 1.0
    return (img - np.float32(med)) / np.float32(spread)


def _smooth_in(a: np.ndarray, support: np.ndarray, sigma_px: tuple[float, float]) -> np.ndarray:
    """Gaussian of ``a`` over ``support`` only (normalised convolution), in-plane."""
    s = (0.0, *sigma_px)
    w = ndi.gaussian_filter(support.astype(np.float32), s, mode="constant")
    v = ndi.gaussian_filter(np.where(support, a, 0.0).astype(np.float32), s, mode="constant")
    return np.where(w > 1e-3, v / np.maximum(w, 1e-3), 0.0).astype(np.float32)


def _depth_mm(mask: np.ndarray, pixel_mm: tuple[float, float]) -> np.ndarray:
    """In-plane distance (mm) from each pixel inside ``mask`` to its edge; 0 outside."""
    out = np.zeros(mask.shape, dtype=np.float32)
    for z in range(mask.shape[0]):
        if mask[z].any():
            out[z] = ndi.distance_transform_edt(mask[z], sampling=pixel_mm)
    return out


def _mirror_source(centre: float, index: np.ndarray, n: int) -> np.ndarray:
    """The index mirrored about ``centre`` of each of ``index`` along an axis of ``n``; clamped."""
    return np.clip(np.rint(2.0 * centre - index).astype(np.intp), 0, n - 1)


def _mirror(a: np.ndarray, lr_axis: int, centre: float, start: int, n: int) -> np.ndarray:
    """``a`` reflected about ``centre`` along ``lr_axis``; edges clamp.

    ``a`` is a crop, beginning at index ``start``, of an axis of ``n`` indices
    (``centre`` is an index of the whole axis); a source outside the crop is
    clamped to it (the crop of :func:`_work_box` holds every source a tissue
    pixel needs).
    """
    m = a.shape[lr_axis]
    src = _mirror_source(centre, np.arange(start, start + m), n)
    return np.take(a, np.clip(src - start, 0, m - 1), axis=lr_axis)


def _work_box(
    cand: np.ndarray, prior: np.ndarray | None, lr_axis: int | None, centre: float
) -> tuple[slice, slice, slice]:
    """The part of the volume the features are computed on: they are the same as on the whole.

    The box of the tissue and the prior, one voxel wider on every side (the
    distance maps' nearest background, and the empty slice beside the first and
    last whose smoothed intensity is the neighbour-slice feature's 0), and
    along ``lr_axis`` wide enough to hold the mirror of every tissue column.
    Every filter is a normalised convolution over the tissue with zero
    padding, so it gives the same values inside the box as on the whole
    volume, bit for bit (``test_features_are_computed_on_the_tissue_box_alone``).
    """
    both = cand if prior is None else cand | prior
    box = true_box(both)
    tissue = true_box(cand)
    assert box is not None and tissue is not None  # the caller checked the tissue
    out = []
    for axis, (s, n) in enumerate(zip(box, cand.shape, strict=True)):
        lo, hi = max(int(s.start) - 1, 0), min(int(s.stop) + 1, n)
        if axis == lr_axis:
            t = tissue[axis]
            src = _mirror_source(centre, np.arange(t.start, t.stop), n)
            lo, hi = min(lo, int(src.min())), max(hi, int(src.max()) + 1)
        out.append(slice(lo, hi))
    return out[0], out[1], out[2]


def _prior_columns(
    prior: np.ndarray | None, shape: tuple[int, ...], pixel_mm: tuple[float, float]
) -> list[np.ndarray]:
    """Inside, signed distance (mm) and slice-area share of a prior mask."""
    clip = PRIOR_DISTANCE_CLIP_MM
    prior = np.zeros(shape, bool) if prior is None else np.asarray(prior, dtype=bool)
    dist = np.full(shape, clip, np.float32)
    for z in range(shape[0]):
        if prior[z].any():
            outside = ndi.distance_transform_edt(~prior[z], sampling=pixel_mm)
            inside = ndi.distance_transform_edt(prior[z], sampling=pixel_mm)
            dist[z] = np.clip(outside - inside, -clip, clip)
    area = prior.sum(axis=(1, 2)).astype(np.float32)
    share = np.broadcast_to((area / max(float(area.max()), 1.0))[:, None, None], shape)
    return [prior.astype(np.float32), dist, share]


def compute_features(
    image: np.ndarray,
    *,
    spacing_mm: tuple[float, float, float],
    modality: str,
    lr_axis: int | None = 2,
    prior: np.ndarray | None = None,
    candidates: np.ndarray | None = None,
) -> PatientFeatures:
    """The rows of :data:`FEATURE_NAMES` for every tissue pixel of one patient.

    Intensities are normalised by the tissue deeper than
    :data:`REFERENCE_DEPTH_MM` (the brain, in a head or alone); depths and
    positions are taken on the tissue (:func:`tissue_foreground`).

    Parameters
    ----------
    image : (z, y, x) ndarray of real numbers
        The slices as acquired (any intensity scale). Not modified.
    spacing_mm : (3,) tuple of float
        ``(slice step, row, column)`` spacing, mm.
    modality : {"flair", "t2", "t1c"}
        The sequence (a feature of its own).
    lr_axis : {1, 2} or None
        Left-right array axis (mirror features); None = no mirror (the
        asymmetry features are then 0).
    prior : (z, y, x) ndarray of bool, optional
        A rule-based segmentation of the same slices (the robust lesion
        model's mask): its inside, the signed in-plane distance to its
        boundary (mm, negative inside, clipped at
        :data:`PRIOR_DISTANCE_CLIP_MM`) and its slice's share of its largest
        slice area are features, so the model learns when to trust it.
        None = an empty prior.
    candidates : (z, y, x) ndarray of bool, optional
        The tissue to give rows to, instead of this image's own
        :func:`tissue_foreground`: another co-registered sequence's, so that
        several sequences of one patient have rows for the same pixels
        (:mod:`tumor3d.learned.multiseq`). None = this image's tissue.

    Returns
    -------
    PatientFeatures

    Examples
    --------
    >>> img = np.zeros((3, 48, 48)); img[:, 4:44, 4:44] = 100.0; img[1, 20:26, 10:16] = 200.0
    >>> f = compute_features(img, spacing_mm=(5.0, 1.0, 1.0), modality="flair")
    >>> f.values.shape[1] == len(FEATURE_NAMES), int(f.candidates.sum())
    (True, 4800)
    """
    img = _check_image(image)
    mod = str(modality).strip().lower()
    if mod not in MODALITY_CODES:
        raise InputError(f"unknown modality {modality!r}: expected one of {sorted(MODALITY_CODES)}")
    sp = tuple(float(v) for v in np.ravel(spacing_mm))
    if len(sp) != 3 or not all(np.isfinite(v) and v > 0 for v in sp):
        raise InputError(f"spacing_mm must be three positive numbers, got {spacing_mm}")
    if lr_axis not in (None, 1, 2):
        raise InputError(f"lr_axis must be 1, 2 or None, got {lr_axis}")
    pixel_mm = (sp[1], sp[2])
    if candidates is None:
        cand = tissue_foreground(img)
    else:
        cand = np.asarray(candidates, dtype=bool)
        if cand.shape != img.shape:
            raise InputError(f"candidates shape {cand.shape} differs from the image's {img.shape}")
    if not cand.any():
        raise InputError("no tissue: the image holds no structure brighter than its background")
    if prior is not None:
        prior = np.asarray(prior, dtype=bool)
        if prior.shape != img.shape:
            raise InputError(f"prior mask shape {prior.shape} differs from the image's {img.shape}")
    # left-right asymmetry about the tissue's centre of mass along the left-right axis
    centre = 0.0
    if lr_axis is not None:
        other = tuple(a for a in range(3) if a != lr_axis)
        profile = cand.sum(axis=other).astype(np.float64)
        centre = float(np.sum(profile * np.arange(profile.size)) / profile.sum())
    # every column is computed on the tissue's box alone (the same values as on the whole
    # volume: _work_box), and only the tissue's pixels get rows
    box = _work_box(cand, prior, lr_axis, centre)
    start = [int(b.start) for b in box]
    full_cand = cand
    img, cand = img[box], cand[box]
    if prior is not None:
        prior = prior[box]
    depth = _depth_mm(cand, pixel_mm)
    deep = depth >= REFERENCE_DEPTH_MM
    if deep.sum() < 1000:  # a small field of view: the tissue's inner half
        deep = depth >= 0.5 * depth.max()
    norm = normalise_intensity(img, deep)
    nz = img.shape[0]

    def px(mm: float) -> tuple[float, float]:
        return (mm / pixel_mm[0], mm / pixel_mm[1])

    cols: list[np.ndarray] = [norm]
    smooth = {s: _smooth_in(norm, cand, px(s)) for s in _SMOOTH_MM}
    cols += [smooth[s] for s in _SMOOTH_MM]
    for s in (2.0, 4.0):
        sq = _smooth_in(norm * norm, cand, px(s))
        cols.append(np.sqrt(np.maximum(sq - smooth[s] ** 2, 0.0)))
    for s in (2.0, 4.0, 8.0):  # no left-right axis: no asymmetry (0)
        if lr_axis is None:
            cols.append(np.zeros_like(norm))
            continue
        mirrored = _mirror(smooth[s], lr_axis, centre, start[lr_axis], full_cand.shape[lr_axis])
        cols.append(smooth[s] - mirrored)
    # the neighbouring slices at the same pixel (3-D context; edge slices repeat)
    s2 = smooth[2.0]
    up = np.concatenate([s2[1:], s2[-1:]], axis=0)
    down = np.concatenate([s2[:1], s2[:-1]], axis=0)
    cols.append(0.5 * (up + down))
    cols.append(smooth[4.0] - smooth[16.0])  # a difference of Gaussians: blobs
    # each slice's own level: excess over the median of its deep tissue, and its top
    slice_med = np.zeros(nz, np.float32)
    slice_p99 = np.zeros(nz, np.float32)
    for z in range(nz):
        region = deep[z] if deep[z].sum() >= 100 else cand[z]
        v = s2[z][region]
        if v.size:
            slice_med[z], slice_p99[z] = np.percentile(v, [50.0, 99.0])
    cols.append(s2 - slice_med[:, None, None])
    cols.append(np.broadcast_to(slice_p99[:, None, None], img.shape))
    cols.append(np.full(img.shape, float(np.percentile(s2[deep], 99.0)), np.float32))
    cols.append(depth)
    max_depth = depth.reshape(nz, -1).max(axis=1)
    cols.append(depth / np.maximum(max_depth, 1e-3)[:, None, None])
    # position in the tissue's box: left-right offset from the centre (abs), front-back,
    # slice position through the tissue's extent, the slice's share of the largest area
    # (indices of the whole volume)
    zs, ys, xs = (c + o for c, o in zip(np.nonzero(cand), start, strict=True))
    grid = [
        np.arange(o, o + n, dtype=np.float32).reshape([-1 if a == k else 1 for a in range(3)])
        for k, (o, n) in enumerate(zip(start, img.shape, strict=True))
    ]
    lr = lr_axis if lr_axis is not None else 2
    ap = 1 if lr == 2 else 2
    lo = [zs.min(), ys.min(), xs.min()]
    hi = [zs.max(), ys.max(), xs.max()]
    half = max(0.5 * (hi[lr] - lo[lr]), 1.0)
    cols.append(np.abs(grid[lr] - centre) / half if lr_axis is not None else np.zeros_like(norm))
    cols.append((grid[ap] - lo[ap]) / max(hi[ap] - lo[ap], 1))
    cols.append((grid[0] - lo[0]) / max(hi[0] - lo[0], 1))
    area = cand.sum(axis=(1, 2)).astype(np.float32)
    cols.append(np.broadcast_to((area / max(area.max(), 1.0))[:, None, None], img.shape))
    cols.append(np.full(img.shape, MODALITY_CODES[mod], np.float32))
    cols += _prior_columns(prior, img.shape, pixel_mm)
    where = np.nonzero(cand)
    values = np.empty((where[0].size, len(cols)), dtype=np.float32)
    for j, c in enumerate(cols):
        values[:, j] = np.broadcast_to(c, img.shape)[where]
    index = np.ravel_multi_index(
        tuple(w + o for w, o in zip(where, start, strict=True)), full_cand.shape
    )
    return PatientFeatures(values, index.astype(np.int64), full_cand.shape, full_cand)
