"""The paper method's tumour cluster on one slice.

The ``LL/2`` histograms, the patient's normal-tissue centres, the choice of the
tumour cluster and its filled component (steps 1-4 of the package docstring).
"""

from __future__ import annotations

import numpy as np
import pywt
from scipy import ndimage as ndi
from scipy.optimize import linear_sum_assignment
from skimage.morphology import disk

from tumor3d.segmentation.fcm import _fcm_histogram
from tumor3d.segmentation.segment.result import N_GRAY


def _ll_histograms(enhanced: np.ndarray, brain: np.ndarray) -> np.ndarray:
    """(z, 256) histograms of the Haar ``LL/2`` band over fully-brain 2x2 blocks.

    ``LL/2`` of ``pywt.dwt2(..., 'haar')`` is the 2x2 block mean, rounded to
    the nearest gray level. A block counts only if all four of its pixels
    are brain: a block straddling the brain border would mix the zeroed
    background into the mean and create spurious dark values. An odd last
    row/column is left out of the histogram (labelling is unaffected). A
    slice without a complete brain block falls back to the histogram of its
    full-resolution brain pixels.
    """
    nz, ny, nx = enhanced.shape
    ey, ex = ny - ny % 2, nx - nx % 2
    hists = np.zeros((nz, N_GRAY), dtype=np.float64)
    if ey >= 2 and ex >= 2:
        img = enhanced[:, :ey, :ex].astype(np.float64)
        ll = pywt.dwt2(img, "haar", axes=(-2, -1))[0] / 2.0
        blocks = brain[:, :ey, :ex].reshape(nz, ey // 2, 2, ex // 2, 2).all(axis=(2, 4))
        levels = np.clip(np.floor(ll + 0.5), 0, N_GRAY - 1).astype(np.intp)
        zz = np.broadcast_to(np.arange(nz, dtype=np.intp)[:, None, None], levels.shape)
        keys = zz[blocks] * N_GRAY + levels[blocks]
        hists = np.bincount(keys, minlength=nz * N_GRAY).reshape(nz, N_GRAY).astype(np.float64)
    empty = hists.sum(axis=1) == 0
    for z in np.flatnonzero(empty):
        hists[z] = np.bincount(enhanced[z][brain[z]], minlength=N_GRAY)
    return hists


def _reference_centers(pooled: np.ndarray, m: float, tol: float, max_num_iter: int) -> np.ndarray:
    """[A8]: three ascending centres from FCM (C = 3) on the pooled normal histogram."""
    if not pooled.sum() > 0:
        return np.full(3, np.nan)
    cdf = np.cumsum(pooled) / pooled.sum()
    seeds = np.searchsorted(cdf, [1 / 6, 1 / 2, 5 / 6]).astype(np.float64)
    seeds = seeds + np.array([-0.25, 0.0, 0.25])  # distinct even if the quantiles coincide
    v, _ = _fcm_histogram(pooled, seeds, m, tol, max_num_iter)
    return np.sort(v)


def _plausible(v: np.ndarray, ref: np.ndarray, modality: str) -> np.ndarray:
    """Whether each centre is plausible for a tumour given the normal-tissue centres."""
    if not np.all(np.isfinite(ref)):
        return np.ones(v.size, dtype=bool)
    # T2 and T1c: brighter than the middle tissue (GM); FLAIR: brighter than all
    # normal tissue (the CSF is suppressed, the lesion is the hyperintensity).
    floor = ref[2] if modality == "flair" else ref[1]
    return v > floor


def _rule_cluster(v: np.ndarray, modality: str) -> int:
    """Fallback without references: T2 second-brightest, FLAIR / T1c brightest."""
    order = np.argsort(v)
    if modality == "t2" and v.size >= 3:
        return int(order[-2])
    return int(order[-1])


def _choose_tumor_cluster(
    v: np.ndarray, ref: np.ndarray, modality: str, mass: np.ndarray | None = None
) -> tuple[int, str]:
    """[A8]: index of the tumour cluster among centres ``v`` and how it was chosen.

    ``mass`` (optional, per cluster) is the number of brain pixels labelled
    with each cluster. When several unmatched clusters are plausible, the
    most populous is the tumour: an extra unmatched cluster is the sparse
    partial volume between two tissues (measured on a phantom slice: 397
    partial-volume pixels at gray 162 against 1440 tumour pixels at 202,
    where "farthest from the references" chose the former).
    """
    if v.size < 2:
        return -1, "none"
    plausible = _plausible(v, ref, modality)
    if np.all(np.isfinite(ref)):
        dist = np.abs(v[:, None] - ref[None, :])  # (k, 3)
        cost = dist.copy()
        brightest = int(np.argmax(v))
        if modality == "t2" and v[brightest] >= ref[2]:
            # On T2 nothing in the brain is brighter than CSF: a cluster at or
            # above the CSF reference is CSF. Pin it there, so that a CSF
            # reference pulled down by partial volume (the CSF rim is only a
            # few pixels thick) cannot leave real CSF "unmatched".
            plausible[brightest] = False
            cost[brightest, :] = np.abs(cost).max() * 10.0 + 1.0
            cost[brightest, 2] = 0.0
        rows, _ = linear_sum_assignment(cost)
        unmatched = np.setdiff1d(np.arange(v.size), rows)
        nearest = dist.min(axis=1)
        # unmatched clusters first; failing those, any cluster that is not a
        # normal tissue, i.e. lies farther than half the closest reference gap
        # from every reference centre
        distinct = nearest > 0.5 * np.min(np.diff(ref))
        score = nearest if mass is None else np.asarray(mass, dtype=np.float64)
        for candidates in (unmatched, np.flatnonzero(distinct)):
            candidates = candidates[plausible[candidates]]
            if candidates.size:
                return int(candidates[np.argmax(score[candidates])]), "reference"
        return -1, "none"
    idx = _rule_cluster(v, modality)
    return idx, "rule"


def _largest_component_filled(mask: np.ndarray) -> np.ndarray:
    labels, n = ndi.label(mask)  # 2-D default structure: 4-connectivity
    if n == 0:
        return mask
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return ndi.binary_fill_holes(labels == int(np.argmax(sizes)))


def _tumor_component(cluster: np.ndarray, brain: np.ndarray, rim_px: int) -> np.ndarray:
    """Largest 4-connected tumour component chosen away from the brain's rim, holes filled.

    The component is chosen among cluster pixels at least ``rim_px`` inside
    the brain mask, then regains the cluster pixels within ``rim_px + 1`` of
    it (its own border, even where it touches the cortex), and its holes are
    filled. A partial-volume rim along the brain boundary is thus never
    chosen, nor followed around the brain, nor filled into a disc.
    """
    if rim_px <= 0:
        return _largest_component_filled(cluster)
    footprint = disk(rim_px).astype(bool)
    interior = cluster & ndi.binary_erosion(brain, structure=footprint, border_value=0)
    labels, n = ndi.label(interior)
    if n == 0:
        return interior
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    core = labels == int(np.argmax(sizes))
    grown = cluster & ndi.binary_dilation(core, structure=disk(rim_px + 1).astype(bool))
    # keep the part of the regrown set connected to the core
    labels, _ = ndi.label(grown)
    keep = np.unique(labels[core])
    return ndi.binary_fill_holes(np.isin(labels, keep[keep > 0]))
