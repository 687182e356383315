r"""Agreement measures between a segmentation and a reference (pure numpy/scipy).

Overlap
    :func:`dice` :math:`D = 2|A \cap B| / (|A| + |B|)`,
    :func:`jaccard` :math:`J = |A \cap B| / |A \cup B|`; both ``nan`` when
    ``A`` and ``B`` are both empty (undefined, not "perfect").
Counts
    :func:`relative_error_percent` -- Eq. 9 of Arakeri & Reddy (2013),
    :math:`\epsilon = |N_p - N_g| / N_g \times 100`;
    :func:`slice_confusion` -- the paper's Table 2: a slice is *truly*
    abnormal iff the reference has tumour on it.
Agreement of two measurement methods
    :func:`bland_altman` -- mean bias and 95 % limits of agreement
    (Bland & Altman, Lancet 1986): ``bias = mean(d)``,
    ``LoA = bias -/+ 1.96 sd(d)`` with ``d = estimate - reference`` and the
    sample standard deviation (``ddof = 1``).
Surface distances (mm)
    :func:`surface_distances_mm` (two masks on one voxel grid, anisotropic
    spacing) and :func:`surface_distances_world_mm` (two masks on different
    grids of one world space); :func:`hausdorff_mm` summarises them as the
    maximum and the 95th-percentile symmetric surface distance.

Surface convention
------------------
The *surface* of a binary mask is its set of boundary voxels: the voxels of
the mask with at least one 6-neighbour outside it (the volume border counts
as outside). Distances are between boundary-voxel centres, in millimetres,
as in MONAI's and DeepMind's ``surface-distance`` mask-based metrics. For
two concentric balls of radii ``r1 < r2`` the Hausdorff distance is
``r2 - r1`` within one voxel diagonal.

On one grid the directed distances come from scipy's exact Euclidean
distance transform with ``sampling = spacing`` (Maurer et al. 2003), cropped
to the bounding box of both masks (which changes nothing: every boundary
voxel lies inside it). On different grids, the boundary-voxel centres of each
mask are mapped to world millimetres by its own affine and the nearest
boundary point of the other mask is found with a k-d tree
(:class:`scipy.spatial.cKDTree`); the two give identical results on one grid.

``HD95`` follows MONAI and DeepMind: the larger of the two *directed* 95th
percentiles, ``max(P95(d(A->B)), P95(d(B->A)))``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from tumor3d.errors import InputError

__all__ = [
    "BlandAltman",
    "SliceConfusion",
    "SurfaceDistances",
    "bland_altman",
    "boundary_voxels",
    "dice",
    "hausdorff_mm",
    "jaccard",
    "overlap_counts",
    "point_set_distances_mm",
    "relative_error_percent",
    "signed_percent_error",
    "slice_confusion",
    "surface_distances_mm",
    "surface_distances_world_mm",
]


# --------------------------------------------------------------------------- validation


def _binary(mask: object, name: str, ndim: int | None = None) -> np.ndarray:
    if not isinstance(mask, np.ndarray):
        raise TypeError(f"{name} must be a numpy array, got {type(mask).__name__}")
    if ndim is not None and mask.ndim != ndim:
        raise InputError(f"{name} must be {ndim}-D, got shape {mask.shape}")
    if mask.dtype == bool:
        return mask
    if not (np.issubdtype(mask.dtype, np.integer) or np.issubdtype(mask.dtype, np.floating)):
        raise TypeError(f"{name} must be a boolean or numeric array, got dtype {mask.dtype}")
    if not np.all(np.isin(mask, (0, 1))):
        raise InputError(f"{name} must be binary (only 0 and 1), got other values")
    return mask.astype(bool)


def _same_shape(a: np.ndarray, b: np.ndarray, na: str, nb: str) -> None:
    if a.shape != b.shape:
        raise InputError(f"{na} and {nb} must have the same shape, got {a.shape} and {b.shape}")


def _spacing(spacing_mm: object, ndim: int) -> np.ndarray:
    try:
        s = np.asarray(spacing_mm, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise TypeError(f"spacing_mm must be {ndim} numbers, got {spacing_mm!r}") from None
    if s.size == 1:
        s = np.repeat(s, ndim)
    if s.size != ndim or not np.all(np.isfinite(s)) or np.any(s <= 0):
        raise InputError(f"spacing_mm must be {ndim} positive finite mm values, got {spacing_mm!r}")
    return s


def _affine(affine: object, name: str) -> np.ndarray:
    a = np.asarray(affine, dtype=np.float64)
    if a.shape != (4, 4) or not np.all(np.isfinite(a)):
        raise InputError(f"{name} must be a finite 4x4 matrix, got shape {a.shape}")
    if abs(np.linalg.det(a[:3, :3])) < 1e-12:
        raise InputError(f"{name} is singular")
    return a


# --------------------------------------------------------------------------- overlap


def overlap_counts(pred: np.ndarray, ref: np.ndarray) -> tuple[int, int, int]:
    """Return ``(|A ∩ B|, |A|, |B|)`` for two binary masks of one shape.

    Parameters
    ----------
    pred, ref : ndarray of bool (or 0/1), any equal shape
        ``A`` = prediction, ``B`` = reference.
    """
    a = _binary(pred, "pred")
    b = _binary(ref, "ref")
    _same_shape(a, b, "pred", "ref")
    return int(np.count_nonzero(a & b)), int(np.count_nonzero(a)), int(np.count_nonzero(b))


def dice(pred: np.ndarray, ref: np.ndarray) -> float:
    r"""Dice coefficient :math:`2|A \cap B| / (|A| + |B|)` in ``[0, 1]``.

    Parameters
    ----------
    pred, ref : ndarray of bool (or 0/1), any equal shape

    Returns
    -------
    float
        ``nan`` when both masks are empty (undefined).
    """
    inter, na, nb = overlap_counts(pred, ref)
    return float("nan") if na + nb == 0 else 2.0 * inter / (na + nb)


def jaccard(pred: np.ndarray, ref: np.ndarray) -> float:
    r"""Jaccard index :math:`|A \cap B| / |A \cup B|` in ``[0, 1]`` (``nan`` if both empty)."""
    inter, na, nb = overlap_counts(pred, ref)
    union = na + nb - inter
    return float("nan") if union == 0 else inter / union


# --------------------------------------------------------------------------- counts


def relative_error_percent(n_pred: float, n_ref: float) -> float:
    r"""Eq. 9: :math:`\epsilon = |N_p - N_g| / N_g \times 100`.

    Parameters
    ----------
    n_pred, n_ref : float
        ``N_p`` (method) and ``N_g`` (reference), e.g. tumour pixel counts or
        volumes in mm^3; both >= 0.

    Returns
    -------
    float
        Percent; ``nan`` when ``N_g = 0`` (undefined). Counts are checked
        (>= 0) here; Eq. 9 itself is :func:`tumor3d.metrics.relative_error_percent`.
    """
    from tumor3d.metrics import relative_error_percent as eq9

    return eq9(_count(n_pred, "n_pred"), _count(n_ref, "n_ref"), zero_truth="nan")


def signed_percent_error(estimate: float, reference: float) -> float:
    r"""Signed error :math:`(E - R) / R \times 100` (``nan`` when ``R = 0``)."""
    e = _count(estimate, "estimate")
    r = _count(reference, "reference")
    return float("nan") if r == 0 else (e - r) / r * 100.0


def _count(value: object, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating):
        raise TypeError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v) or v < 0:
        raise InputError(f"{name} must be a finite number >= 0, got {value!r}")
    return v


@dataclass(frozen=True)
class SliceConfusion:
    """Table 2 confusion counts of abnormal-slice recognition.

    ``tp`` abnormal slices recognised, ``fn`` abnormal slices missed,
    ``tn`` normal slices passed, ``fp`` normal slices flagged.
    """

    tp: int
    fp: int
    tn: int
    fn: int

    @property
    def sensitivity(self) -> float:
        """Recall ``tp / (tp + fn)`` (``nan`` without abnormal slices)."""
        return self.tp / (self.tp + self.fn) if self.tp + self.fn else float("nan")

    @property
    def specificity(self) -> float:
        """``tn / (tn + fp)`` (``nan`` without normal slices)."""
        return self.tn / (self.tn + self.fp) if self.tn + self.fp else float("nan")

    @property
    def accuracy(self) -> float:
        """``(tp + tn) / n`` (``nan`` for no slices)."""
        n = self.tp + self.fp + self.tn + self.fn
        return (self.tp + self.tn) / n if n else float("nan")

    def __add__(self, other: SliceConfusion) -> SliceConfusion:
        """Pool two sets of counts."""
        return SliceConfusion(
            self.tp + other.tp, self.fp + other.fp, self.tn + other.tn, self.fn + other.fn
        )


def slice_confusion(predicted_abnormal: np.ndarray, ref_tumor_pixels: np.ndarray) -> SliceConfusion:
    """Confusion counts of the paper's Table 2.

    Parameters
    ----------
    predicted_abnormal : (n_slices,) array_like of bool
        The method's verdict per slice (flagged abnormal / has tumour).
    ref_tumor_pixels : (n_slices,) array_like of int
        Reference tumour pixels per slice; a slice is truly abnormal iff > 0.

    Returns
    -------
    SliceConfusion
    """
    p = np.asarray(predicted_abnormal)
    g = np.asarray(ref_tumor_pixels)
    if p.ndim != 1 or g.ndim != 1 or p.shape != g.shape:
        raise InputError(
            f"predicted_abnormal and ref_tumor_pixels must be 1-D of one length, "
            f"got shapes {p.shape} and {g.shape}"
        )
    if p.dtype != bool:
        p = _binary(p, "predicted_abnormal")
    if not (np.issubdtype(g.dtype, np.number) or g.dtype == bool) or np.any(g < 0):
        raise InputError("ref_tumor_pixels must be non-negative counts")
    truth = g > 0
    return SliceConfusion(
        tp=int(np.count_nonzero(p & truth)),
        fp=int(np.count_nonzero(p & ~truth)),
        tn=int(np.count_nonzero(~p & ~truth)),
        fn=int(np.count_nonzero(~p & truth)),
    )


# --------------------------------------------------------------------------- Bland-Altman


@dataclass(frozen=True)
class BlandAltman:
    """Bland-Altman agreement of ``estimate`` with ``reference``.

    ``bias`` = mean difference, ``sd`` = its sample standard deviation,
    ``loa_low``/``loa_high`` = ``bias -/+ 1.96 sd`` (95 % limits of
    agreement), ``n`` = number of pairs; all in the unit of the input.
    """

    bias: float
    sd: float
    loa_low: float
    loa_high: float
    n: int


def bland_altman(estimate: np.ndarray, reference: np.ndarray) -> BlandAltman:
    """Mean bias and 95 % limits of agreement of paired measurements.

    Parameters
    ----------
    estimate, reference : (n,) array_like of float
        Paired values (e.g. volumes in mL); non-finite pairs are dropped.

    Returns
    -------
    BlandAltman
        With ``d = estimate - reference``: ``bias = mean(d)``,
        ``sd = std(d, ddof=1)``, ``LoA = bias -/+ 1.96 sd``; ``sd`` and the
        limits are ``nan`` for fewer than 2 pairs, everything ``nan`` for 0.
    """
    e = np.asarray(estimate, dtype=np.float64).reshape(-1)
    r = np.asarray(reference, dtype=np.float64).reshape(-1)
    if e.shape != r.shape:
        raise InputError(
            f"estimate and reference must have one length, got {e.size} and {r.size}"
        )
    keep = np.isfinite(e) & np.isfinite(r)
    d = e[keep] - r[keep]
    n = int(d.size)
    if n == 0:
        nan = float("nan")
        return BlandAltman(nan, nan, nan, nan, 0)
    bias = float(d.mean())
    sd = float(d.std(ddof=1)) if n > 1 else float("nan")
    return BlandAltman(bias, sd, bias - 1.96 * sd, bias + 1.96 * sd, n)


# --------------------------------------------------------------------------- surfaces


@dataclass(frozen=True)
class SurfaceDistances:
    """Directed boundary-to-boundary distances in mm.

    ``pred_to_ref[i]`` is the distance from the ``i``-th boundary voxel of
    the prediction to the nearest boundary voxel of the reference, and
    ``ref_to_pred`` the other way round. Both empty when a mask is empty.
    """

    pred_to_ref: np.ndarray
    ref_to_pred: np.ndarray

    @property
    def defined(self) -> bool:
        """Whether both masks had a surface."""
        return self.pred_to_ref.size > 0 and self.ref_to_pred.size > 0


def boundary_voxels(mask: np.ndarray) -> np.ndarray:
    """Boundary of a binary mask: its voxels with a 6-neighbour outside it.

    Parameters
    ----------
    mask : ndarray of bool (or 0/1), 2-D or 3-D
        The volume border counts as outside.

    Returns
    -------
    ndarray of bool, same shape
    """
    m = _binary(mask, "mask")
    if m.ndim not in (2, 3):
        raise InputError(f"mask must be 2-D or 3-D, got shape {m.shape}")
    return _boundary(m)


def _boundary(m: np.ndarray) -> np.ndarray:
    structure = ndimage.generate_binary_structure(m.ndim, 1)
    return m & ~ndimage.binary_erosion(m, structure=structure, border_value=0)


def surface_distances_mm(
    pred: np.ndarray, ref: np.ndarray, spacing_mm: object
) -> SurfaceDistances:
    """Directed surface distances (mm) between two masks on one voxel grid.

    Parameters
    ----------
    pred, ref : ndarray of bool (or 0/1), shape (z, y, x) (or any 2-D/3-D, equal)
    spacing_mm : float or sequence of float
        Voxel size along each array axis in mm (anisotropic allowed), e.g.
        ``(dz, dy, dx)``; the grid is assumed orthogonal.

    Returns
    -------
    SurfaceDistances
        Exact Euclidean distances between boundary-voxel centres (see the
        module docstring), from scipy's distance transform with ``sampling``.
    """
    a = _binary(pred, "pred")
    b = _binary(ref, "ref")
    _same_shape(a, b, "pred", "ref")
    if a.ndim not in (2, 3):
        raise InputError(f"pred must be 2-D or 3-D, got shape {a.shape}")
    s = _spacing(spacing_mm, a.ndim)
    ba, bb = _boundary(a), _boundary(b)
    if not ba.any() or not bb.any():
        empty = np.zeros(0, dtype=np.float64)
        return SurfaceDistances(empty, empty.copy())
    union = ba | bb
    box = tuple(
        slice(int(idx.min()), int(idx.max()) + 1) for idx in np.nonzero(union)
    )  # every boundary voxel lies in the box, so cropping is exact
    ba, bb = ba[box], bb[box]
    dist_to_b = ndimage.distance_transform_edt(~bb, sampling=s)
    dist_to_a = ndimage.distance_transform_edt(~ba, sampling=s)
    return SurfaceDistances(
        pred_to_ref=np.asarray(dist_to_b[ba], dtype=np.float64),
        ref_to_pred=np.asarray(dist_to_a[bb], dtype=np.float64),
    )


def surface_distances_world_mm(
    pred: np.ndarray, pred_affine: object, ref: np.ndarray, ref_affine: object
) -> SurfaceDistances:
    """Directed surface distances (mm) between masks on different grids of one world space.

    Each mask's boundary-voxel centres (module docstring) are mapped to world
    millimetres with its own affine and matched to the nearest boundary
    point of the other with a k-d tree. On one grid this equals
    :func:`surface_distances_mm`.

    Parameters
    ----------
    pred, ref : 3-D ndarray of bool (or 0/1)
        Masks in their own voxel order.
    pred_affine, ref_affine : (4, 4) array_like
        Map each array's voxel index ``(i0, i1, i2, 1)`` (array axis order,
        nibabel's convention) to world mm (RAS).

    Returns
    -------
    SurfaceDistances
    """
    a = _binary(pred, "pred", ndim=3)
    b = _binary(ref, "ref", ndim=3)
    aa = _affine(pred_affine, "pred_affine")
    ab = _affine(ref_affine, "ref_affine")
    pa = _world_points(_boundary(a), aa)
    pb = _world_points(_boundary(b), ab)
    if pa.shape[0] == 0 or pb.shape[0] == 0:
        empty = np.zeros(0, dtype=np.float64)
        return SurfaceDistances(empty, empty.copy())
    d_ab, _ = cKDTree(pb).query(pa, k=1)
    d_ba, _ = cKDTree(pa).query(pb, k=1)
    return SurfaceDistances(np.asarray(d_ab, np.float64), np.asarray(d_ba, np.float64))


def point_set_distances_mm(pred_points: np.ndarray, ref_points: np.ndarray) -> SurfaceDistances:
    """Directed nearest-point distances (mm) between two point sets, e.g. mesh vertices.

    Parameters
    ----------
    pred_points, ref_points : (n, 3), (m, 3) array_like of float
        Points in one world space (RAS mm), e.g. the vertices of the
        reconstructed and of the reference surface.

    Returns
    -------
    SurfaceDistances
        ``pred_to_ref[i]`` = distance from ``pred_points[i]`` to the nearest
        reference point (k-d tree), and the other way round; empty arrays
        when either set is empty. Vertex-to-vertex distances exceed the
        point-to-surface ones by at most half the longest edge.
    """
    a = np.asarray(pred_points, dtype=np.float64)
    b = np.asarray(ref_points, dtype=np.float64)
    for arr, name in ((a, "pred_points"), (b, "ref_points")):
        if arr.ndim != 2 or arr.shape[1] != 3 or not np.all(np.isfinite(arr)):
            raise InputError(f"{name} must be a finite (n, 3) array, got shape {arr.shape}")
    if a.shape[0] == 0 or b.shape[0] == 0:
        empty = np.zeros(0, dtype=np.float64)
        return SurfaceDistances(empty, empty.copy())
    d_ab, _ = cKDTree(b).query(a, k=1)
    d_ba, _ = cKDTree(a).query(b, k=1)
    return SurfaceDistances(np.asarray(d_ab, np.float64), np.asarray(d_ba, np.float64))


def _world_points(mask: np.ndarray, affine: np.ndarray) -> np.ndarray:
    idx = np.argwhere(mask).astype(np.float64)
    return idx @ affine[:3, :3].T + affine[:3, 3]


def hausdorff_mm(distances: SurfaceDistances, percentile: float = 95.0) -> tuple[float, float]:
    """Maximum and percentile symmetric surface distance (Hausdorff) in mm.

    Parameters
    ----------
    distances : SurfaceDistances
    percentile : float, default 95
        In ``(0, 100]``.

    Returns
    -------
    (hd_percentile_mm, hd_max_mm) : tuple of float
        ``max(P(d(A->B)), P(d(B->A)))`` and ``max(max d(A->B), max d(B->A))``;
        both ``nan`` when a mask has no surface.
    """
    if not isinstance(distances, SurfaceDistances):
        raise TypeError(f"distances must be SurfaceDistances, got {type(distances).__name__}")
    q = float(percentile)
    if not 0.0 < q <= 100.0:
        raise InputError(f"percentile must be in (0, 100], got {percentile!r}")
    if not distances.defined:
        return float("nan"), float("nan")
    hp = max(
        float(np.percentile(distances.pred_to_ref, q)),
        float(np.percentile(distances.ref_to_pred, q)),
    )
    hmax = max(float(distances.pred_to_ref.max()), float(distances.ref_to_pred.max()))
    return hp, hmax
