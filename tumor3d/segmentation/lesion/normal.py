"""Step 1 and step 3e: the patient-pooled model of normal tissue and its tail.

The median / MAD model of the smoothed brain intensities (step 1 of
:mod:`tumor3d.segmentation.lesion`), the CSF threshold of T2 (step 6) and
the level of normal tissue's own outliers a candidate must exceed (step 3e).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.special
from scipy import ndimage as ndi

_MAD_TO_SIGMA = 1.4826  # sigma of a normal distribution = 1.4826 MAD


#: Step 3e (FLAIR): a candidate's seeds must have their median smoothed gray at
#: least at this upper quantile of the normal model's tail beyond the seed level (the
#: level above which only this share of normal tissue's seeds lie): see
#: normal_tail_level and the package docstring.
TAIL_QUANTILE = 0.25


@dataclass(frozen=True)
class NormalModel:
    """Patient-pooled intensity model of normal brain tissue (smoothed gray levels).

    Attributes
    ----------
    median : float
        ``mu``, median of the smoothed brain intensities.
    sigma : float
        ``1.4826 MAD`` of the same intensities.
    seed_threshold : float
        ``mu + seed_sigmas sigma``.
    csf_threshold : float
        Gray level above which T2 voxels are CSF (inf for other modalities).
    """

    median: float
    sigma: float
    seed_threshold: float
    csf_threshold: float


def _smooth_in_brain(img: np.ndarray, brain: np.ndarray, sigma_px: float) -> np.ndarray:
    """In-plane Gaussian smoothing normalised by the smoothed brain mask (no leakage)."""
    if sigma_px <= 0:
        return np.where(brain, img.astype(np.float32), 0.0)
    f = brain.astype(np.float32)
    num = ndi.gaussian_filter(img.astype(np.float32) * f, (0, sigma_px, sigma_px))
    den = ndi.gaussian_filter(f, (0, sigma_px, sigma_px))
    return np.where(brain, num / np.maximum(den, 1e-6), 0.0).astype(np.float32)


def _csf_threshold(img: np.ndarray, brain: np.ndarray, seed_threshold: float) -> float:
    # CSF is the brightest T2 tissue and fills several per cent of the brain, so the
    # 99th percentile of the brain's gray levels lies in pure CSF; a voxel is CSF when
    # it is nearer that level than the lesion seed level (partial-volume midpoint).
    csf_level = float(np.percentile(img[brain], 99.0))
    return 0.5 * (csf_level + float(seed_threshold))


def normal_model(
    smoothed: np.ndarray, img: np.ndarray, brain: np.ndarray, seed_sigmas: float, modality: str
) -> NormalModel:
    """Median / MAD model of the smoothed brain intensities pooled over all slices."""
    vals = smoothed[brain]
    csf = float("inf")
    mu = float(np.median(vals))
    sigma = float(_MAD_TO_SIGMA * np.median(np.abs(vals - mu)))
    sigma = max(sigma, 1.0)  # at least one gray level: a flat image has no outliers
    seed_t = mu + float(seed_sigmas) * sigma
    if modality == "t2":
        csf = _csf_threshold(img, brain, seed_t)
    return NormalModel(mu, sigma, seed_t, csf)


def normal_tail_level(model: NormalModel, quantile: float = TAIL_QUANTILE) -> float:
    """Gray level above which ``quantile`` of the normal model's seeds lie (step 3e).

    Under the model, normal tissue's smoothed gray is ``N(mu, sigma^2)``; its
    seeds are the tail beyond ``seed_threshold`` (``k = (seed_threshold - mu)
    / sigma``). The level ``mu + z sigma`` with ``P(Z > z) = quantile P(Z > k)``
    splits that tail: ``quantile`` of normal tissue's seeds lie above it.

    >>> m = NormalModel(median=100.0, sigma=10.0, seed_threshold=120.0, csf_threshold=np.inf)
    >>> round(normal_tail_level(m, 0.5), 2), round(normal_tail_level(m, 0.25), 2)
    (122.78, 125.31)
    >>> round(normal_tail_level(m, 1.0), 9) == m.seed_threshold  # the whole tail
    True
    >>> far = NormalModel(median=0.0, sigma=1.0, seed_threshold=12.0, csf_threshold=np.inf)
    >>> 12.0 < normal_tail_level(far) < 12.2  # a high seed level: finite, just above it
    True
    """
    if not 0.0 < quantile <= 1.0:
        raise ValueError(f"quantile must lie in (0, 1], got {quantile}")
    k = (model.seed_threshold - model.median) / model.sigma
    # P(Z > z) = quantile P(Z > k), i.e. z = -ndtri(quantile ndtr(-k)): no 1 - p, so no
    # cancellation for a large k (1 - p rounds to 1 from k of about 8)
    z = -float(scipy.special.ndtri(quantile * scipy.special.ndtr(-k)))
    return model.median + z * model.sigma


def _beyond_normal_tail(seed_gray: np.ndarray, model: NormalModel) -> bool:
    """Step 3e: whether the median of a candidate's seeds (smoothed gray) is beyond the tail."""
    level = normal_tail_level(model, TAIL_QUANTILE)
    return bool(seed_gray.size) and float(np.median(seed_gray)) >= level


def _passing_ids(
    labels: np.ndarray, ids: np.ndarray, sm: np.ndarray, model: NormalModel
) -> np.ndarray:
    """Step 3e on labelled components: the ``ids`` (order kept) whose gray passes.

    One sort of the labelled voxels by label, not a pass over the volume per
    component; each component is judged by :func:`_beyond_normal_tail`.
    """
    on = labels > 0
    lab, val = labels[on], sm[on]
    order = np.argsort(lab, kind="stable")
    lab, val = lab[order], val[order]
    start = np.searchsorted(lab, ids, side="left")
    stop = np.searchsorted(lab, ids, side="right")
    keep = [
        i for i, a, z in zip(ids, start, stop, strict=True) if _beyond_normal_tail(val[a:z], model)
    ]
    return np.asarray(keep, dtype=np.asarray(ids).dtype)


def _passing_components(mask: np.ndarray, sm: np.ndarray, model: NormalModel) -> np.ndarray:
    """The 26-connected components of ``mask`` whose smoothed gray passes step 3e."""
    labels, n = ndi.label(mask, structure=np.ones((3, 3, 3), dtype=bool))
    if n == 0:
        return mask.copy()
    return np.isin(labels, _passing_ids(labels, np.arange(1, n + 1), sm, model))
