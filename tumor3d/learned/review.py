"""When to check a learned segmentation: figures of its own probability map.

A segmentation whose volume is likely to be wrong shows it in the model's
probability: many voxels near the threshold around the lesion (the
boundary is uncertain, the volume with it), a lesion of low mean
probability, or much probability left outside what was kept (a second
lesion or a leak the post-processing cut). :func:`review_features`
computes those figures, :func:`review_segmentation` turns them into
``needs_review`` with its reasons and a ``quality_score`` in [0, 1]. The
limits are chosen by cross-validation by patient
(``benchmarks/learned_cv.py``, ``reports/model_card.md``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tumor3d.errors import InputError

__all__ = ["REVIEW_LIMITS", "Review", "review_features", "review_segmentation"]

#: Limits beyond which a segmentation asks for a human (see the module docstring).
REVIEW_LIMITS: dict[str, float] = {
    # chosen by cross-validation by patient (benchmarks/review_cv.py, reports/learned_cv.md)
    "uncertain_ratio": 3.0,  # voxels with 0.2 < p < 0.8 per lesion voxel (1.2 on the forest alone)
    "mean_probability": 0.85,  # mean probability inside the lesion (below: check)
    "outside_ratio": 0.2,  # probability mass above 0.5 outside the kept lesion, per inside
    "prior_agreement": 0.0,  # Dice of the lesion with the rule-based prior (below: check)
}


@dataclass(frozen=True)
class Review:
    """``needs_review`` with its reasons, and a score (1 = nothing doubtful)."""

    needs_review: bool
    reasons: tuple[str, ...]
    quality_score: float
    figures: dict[str, float]


def review_features(
    probability: np.ndarray,
    mask: np.ndarray,
    spacing_mm: tuple[float, float, float],
    prior: np.ndarray | None = None,
) -> dict[str, float]:
    """Figures of a probability map and the lesion kept from it.

    Returns
    -------
    dict
        ``uncertain_ratio`` (voxels with ``0.2 < p < 0.8`` per lesion voxel;
        inf for an empty lesion with uncertain voxels, 0 when both are empty),
        ``mean_probability`` (inside the lesion; nan when empty),
        ``outside_ratio`` (summed ``p > 0.5`` outside the lesion per summed
        ``p`` inside), ``volume_ml``, ``prior_agreement`` (Dice of the
        lesion with ``prior``, the rule-based mask the model refined; 1 when
        both are empty or no prior is given).

    Examples
    --------
    >>> p = np.zeros((1, 4, 4), np.float32); p[0, :2, :2] = 0.9
    >>> review_features(p, p > 0.5, (1.0, 1.0, 1.0))["uncertain_ratio"]
    0.0
    """
    p = np.asarray(probability, dtype=np.float32)
    m = np.asarray(mask, dtype=bool)
    if p.shape != m.shape:
        raise InputError(f"probability shape {p.shape} does not match mask shape {m.shape}")
    n_in = int(m.sum())
    uncertain = int(np.count_nonzero((p > 0.2) & (p < 0.8)))
    inside = float(p[m].sum())
    outside = float(p[(~m) & (p > 0.5)].sum())
    if n_in:
        ratio = uncertain / n_in
        out_ratio = outside / max(inside, 1e-9)
    else:
        ratio = float("inf") if uncertain else 0.0
        out_ratio = float("inf") if outside else 0.0
    agreement = 1.0
    if prior is not None:
        q = np.asarray(prior, dtype=bool)
        total = int(q.sum()) + n_in
        agreement = 2.0 * int(np.count_nonzero(q & m)) / total if total else 1.0
    return {
        "uncertain_ratio": float(ratio),
        "mean_probability": float(p[m].mean()) if n_in else float("nan"),
        "outside_ratio": float(out_ratio),
        "volume_ml": n_in * float(np.prod(spacing_mm)) / 1000.0,
        "prior_agreement": float(agreement),
    }


def review_segmentation(
    figures: dict[str, float], limits: dict[str, float] | None = None
) -> Review:
    """Whether a human should check the segmentation, and why.

    Examples
    --------
    >>> review_segmentation({"uncertain_ratio": 0.1, "mean_probability": 0.95,
    ...                      "outside_ratio": 0.0, "volume_ml": 20.0}).needs_review
    False
    """
    lim = dict(REVIEW_LIMITS)
    lim.update(limits or {})
    reasons = []
    u = figures["uncertain_ratio"]
    if u > lim["uncertain_ratio"]:
        reasons.append(
            f"uncertain boundary: {u:.2f} voxels of probability 0.2-0.8 per lesion voxel "
            f"(limit {lim['uncertain_ratio']:.2f})"
        )
    mp = figures["mean_probability"]
    if np.isfinite(mp) and mp < lim["mean_probability"]:
        reasons.append(
            f"low confidence: mean lesion probability {mp:.2f} "
            f"(limit {lim['mean_probability']:.2f})"
        )
    o = figures["outside_ratio"]
    if o > lim["outside_ratio"]:
        reasons.append(
            f"lesion-like tissue left outside the kept lesion: {o:.2f} of its probability "
            f"(limit {lim['outside_ratio']:.2f})"
        )
    a = figures.get("prior_agreement", 1.0)
    if a < lim["prior_agreement"]:
        reasons.append(
            f"the model and the rule-based lesion disagree: Dice {a:.2f} between them "
            f"(limit {lim['prior_agreement']:.2f})"
        )
    # score: 1 - the largest excess over the limits, squashed into [0, 1]
    excess = max(
        (1.0 - a) / max(1.0 - lim["prior_agreement"], 1e-6),
        u / lim["uncertain_ratio"] if np.isfinite(u) else 10.0,
        (1.0 - mp) / (1.0 - lim["mean_probability"]) if np.isfinite(mp) else 0.0,
        o / lim["outside_ratio"] if np.isfinite(o) else 10.0,
    )
    score = float(np.clip(1.0 - 0.5 * excess, 0.0, 1.0))
    return Review(bool(reasons), tuple(reasons), score, dict(figures))
