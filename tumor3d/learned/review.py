"""When to check a learned segmentation: figures of its own probability map.

A segmentation whose volume is likely to be wrong shows it in the model's
probability: a lesion of low mean probability, much probability left outside
what was kept (a second lesion or a leak the post-processing cut), or, where
the forest's probability is averaged with a U-Net's (FLAIR), the two models
disagreeing on much of the kept lesion (one says tumour, the other not: the
mean's smoother probability hides it from the other figures), or, where the
forest's probability stands alone (T2, T1c, ``segment.learned_cnn: off``), many
voxels near the threshold per lesion voxel (an uncertain boundary).
:func:`review_features` computes those figures (and one more that is reported
but not judged: the agreement with the rule-based prior), :func:`review_segmentation`
turns them into ``needs_review`` with its reasons and a ``quality_score`` in
[0, 1], by the limits of the kind of segmentation (:data:`REVIEW_LIMITS`). The
limits are chosen by cross-validation by patient (``benchmarks/review_cv.py``,
``reports/learned_cv.md``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from tumor3d.errors import InputError

__all__ = [
    "EMPTY_LESION_REASONS",
    "REVIEW_CHECKS",
    "REVIEW_LIMITS",
    "Review",
    "review_features",
    "review_kind",
    "review_segmentation",
]

#: Limits beyond which a segmentation asks for a human, per kind of segmentation
#: (:func:`review_kind`): ``with_net``, the forest's probability averaged with the
#: U-Net ensemble's (FLAIR, as shipped), ``single_net``, averaged with one net (a
#: user's own), and ``forest_alone`` (T2, T1c, ``segment.learned_cnn: off``: no network
#: to judge). Chosen by cross-validation by patient (benchmarks/review_cv.py,
#: reports/learned_cv.md): ``with_net`` on the shipped method's out-of-fold rows
#: (``net_spread`` by a nested choice among the figure sets, over
#: ``model_disagreement``), ``single_net`` on the single 8-epoch net's rows shipped
#: before ("The review of the mean"), ``forest_alone``'s own limit (uncertain_ratio) on
#: the forest's, the first two shared with ``with_net`` (chosen again with the nets
#: trained with the per-slice soft Dice, 2026-12-07: ``outside_ratio`` 0.2 -> 0.5,
#: ``uncertain_ratio`` 1.2 -> 1.0; ``single_net`` keeps its own).
REVIEW_LIMITS: dict[str, dict[str, float]] = {
    "with_net": {
        "mean_probability": 0.85,  # mean probability inside the lesion (below: check)
        "outside_ratio": 0.5,  # probability mass above 0.5 outside the kept lesion, per inside
        "net_spread": 0.1,  # mean (max - min) of the ensemble's nets' probabilities inside
    },
    "single_net": {
        "mean_probability": 0.85,
        "outside_ratio": 0.2,
        "model_disagreement": 0.1,  # share of the lesion where |p_forest - p_net| > 0.5
    },
    "forest_alone": {
        "mean_probability": 0.85,
        "outside_ratio": 0.5,
        "uncertain_ratio": 1.0,  # voxels of probability 0.2-0.8 per lesion voxel
    },
}

#: How each figure is judged: ``"above"`` (a value over the limit asks for a check) or
#: ``"below"``, and the reason's text (``{v}`` the figure, ``{lim}`` the limit). A limit
#: given to :func:`review_segmentation` for any of them is applied.
REVIEW_CHECKS: dict[str, tuple[str, str]] = {
    "uncertain_ratio": (
        "above",
        "uncertain tumour edge, check the outline on the overlay (the volume may be off "
        "either way): {v:.2f} voxels of probability 0.2-0.8 per lesion voxel (limit {lim:.2f})",
    ),
    "mean_probability": (
        "below",
        "low confidence that the outlined region is tumour, check it on the overlay: mean "
        "lesion probability {v:.2f} (limit {lim:.2f})",
    ),
    "outside_ratio": (
        "above",
        "tumour-like tissue left outside the outline, check around it (the volume may be too "
        "small): {v:.2f} of the lesion probability (limit {lim:.2f})",
    ),
    "prior_agreement": (
        "below",
        "the model and the rule-based lesion disagree, check the outline: Dice {v:.2f} between "
        "them (limit {lim:.2f})",
    ),
    "model_disagreement": (
        "above",
        "the forest and the U-Net disagree, check the outline: on {v:.0%} of the lesion their "
        "probabilities differ by more than 0.5 (limit {lim:.0%})",
    ),
    "net_spread": (
        "above",
        "the U-Net ensemble's nets disagree on the outline, check its edges: their "
        "probabilities differ by {v:.2f} on average inside the lesion (limit {lim:.2f})",
    ),
}

#: The reason of a ratio that is infinite because no lesion was kept (its denominator),
#: in place of :data:`REVIEW_CHECKS`' text, which would read "inf voxels ... per lesion
#: voxel".
EMPTY_LESION_REASONS: dict[str, str] = {
    "uncertain_ratio": "uncertain tumour edge and no lesion kept, check the overlay for a "
    "missed tumour: voxels of probability 0.2-0.8 (limit {lim:.2f} per lesion voxel)",
    "outside_ratio": "tumour-like tissue found but no lesion kept, check the overlay for a "
    "missed tumour (limit {lim:.2f} of its probability)",
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
    *,
    forest_probability: np.ndarray | None = None,
    cnn_probability: np.ndarray | None = None,
    cnn_members: np.ndarray | None = None,
) -> dict[str, float]:
    """Figures of a probability map and the lesion kept from it.

    Parameters
    ----------
    probability : (z, y, x) ndarray of float
        The probability the lesion was cut from.
    mask : (z, y, x) ndarray of bool
        The lesion.
    spacing_mm : (3,) tuple of float
    prior : (z, y, x) ndarray of bool, optional
        The rule-based mask the model refined.
    forest_probability, cnn_probability : (z, y, x) ndarray of float, optional
        The two probabilities ``probability`` is the mean of
        (:class:`tumor3d.learned.segment.LearnedSegmentation`), both or neither.
    cnn_members : (n_nets, z, y, x) ndarray of float, optional
        The U-Net ensemble's nets' own probabilities (``cnn_probability`` is
        their mean).

    Returns
    -------
    dict
        ``uncertain_ratio`` (voxels with ``0.2 < p < 0.8`` per lesion voxel;
        inf for an empty lesion with uncertain voxels, 0 when both are empty),
        ``mean_probability`` (inside the lesion; nan when empty),
        ``outside_ratio`` (summed ``p > 0.5`` outside the lesion per summed
        ``p`` inside), ``volume_ml``, ``prior_agreement`` (Dice of the
        lesion with ``prior``; 1 when both are empty or no prior is given),
        ``model_disagreement`` (the share of the lesion's voxels where the
        forest's and the network's probabilities differ by more than 0.5;
        nan without the two, 0 for an empty lesion), ``net_spread`` (the mean
        over the lesion's voxels of the largest minus the smallest of the
        ensemble's probabilities, a deep ensemble's spread; nan without at
        least two nets, 0 for an empty lesion).

    Examples
    --------
    >>> p = np.zeros((1, 4, 4), np.float32); p[0, :2, :2] = 0.9
    >>> review_features(p, p > 0.5, (1.0, 1.0, 1.0))["uncertain_ratio"]
    0.0
    >>> f = p.copy(); f[0, 0, :2] = 1.0; n = p.copy(); n[0, 0, :2] = 0.3
    >>> review_features((f + n) / 2, p > 0.5, (1.0, 1.0, 1.0), forest_probability=f,
    ...                 cnn_probability=n)["model_disagreement"]
    0.5
    >>> two = np.stack([n, n + 0.2 * (p > 0.5)])
    >>> round(review_features(p, p > 0.5, (1.0, 1.0, 1.0), cnn_members=two)["net_spread"], 3)
    0.2
    """
    p = np.asarray(probability, dtype=np.float32)
    m = np.asarray(mask, dtype=bool)
    if p.shape != m.shape:
        raise InputError(f"probability shape {p.shape} does not match mask shape {m.shape}")
    if (forest_probability is None) != (cnn_probability is None):
        raise InputError("forest_probability and cnn_probability come together (or neither)")
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
    disagreement = float("nan")
    if forest_probability is not None:
        pf = np.asarray(forest_probability, dtype=np.float32)
        pn = np.asarray(cnn_probability, dtype=np.float32)
        if pf.shape != p.shape or pn.shape != p.shape:
            raise InputError(
                f"forest/cnn probability shapes {pf.shape}, {pn.shape} do not match {p.shape}"
            )
        apart = np.count_nonzero(np.abs(pf[m] - pn[m]) > 0.5)
        disagreement = apart / n_in if n_in else 0.0
    spread = float("nan")
    if cnn_members is not None:
        members = np.asarray(cnn_members, dtype=np.float32)
        if members.ndim != 4 or members.shape[1:] != p.shape:
            raise InputError(f"cnn_members must be (n_nets, *{p.shape}), got shape {members.shape}")
        if len(members) >= 2:
            inside_m = members[:, m]
            spread = float((inside_m.max(axis=0) - inside_m.min(axis=0)).mean()) if n_in else 0.0
    return {
        "uncertain_ratio": float(ratio),
        "mean_probability": float(p[m].mean()) if n_in else float("nan"),
        "outside_ratio": float(out_ratio),
        "volume_ml": n_in * float(np.prod(spacing_mm)) / 1000.0,
        "prior_agreement": float(agreement),
        "model_disagreement": float(disagreement),
        "net_spread": spread,
    }


def review_kind(figures: dict[str, float]) -> str:
    """The key of :data:`REVIEW_LIMITS` that judges ``figures``.

    ``"with_net"`` when they hold an ensemble's spread (a number), ``"single_net"``
    when they hold the forest's and one net's disagreement only, else
    ``"forest_alone"``.

    >>> review_kind({"model_disagreement": 0.1, "net_spread": 0.02})
    'with_net'
    >>> review_kind({"model_disagreement": 0.1, "net_spread": float("nan")})
    'single_net'
    >>> review_kind({"model_disagreement": float("nan")})
    'forest_alone'
    """

    def number(name: str) -> bool:
        v = figures.get(name)
        return v is not None and bool(np.isfinite(float(v)))

    if number("net_spread"):
        return "with_net"
    return "single_net" if number("model_disagreement") else "forest_alone"


def review_segmentation(
    figures: dict[str, float], limits: dict[str, float] | None = None
) -> Review:
    """Whether a human should check the segmentation, and why.

    Every figure with a limit (:data:`REVIEW_LIMITS` of the figures' kind,
    :func:`review_kind`, updated by ``limits``) is judged as :data:`REVIEW_CHECKS`
    says; a figure that is absent or nan (the mean probability of an empty
    lesion) is not. The score is 1 minus half the largest excess over the limits,
    in [0, 1].

    Examples
    --------
    >>> review_segmentation({"uncertain_ratio": 0.1, "mean_probability": 0.95,
    ...                      "outside_ratio": 0.0, "volume_ml": 20.0}).needs_review
    False
    >>> review_segmentation({"uncertain_ratio": 2.0, "mean_probability": 0.95,
    ...                      "outside_ratio": 0.0}).reasons[0][:22]
    'uncertain tumour edge,'
    >>> review_segmentation({"mean_probability": 0.95, "outside_ratio": 0.0,
    ...                      "model_disagreement": 0.4, "net_spread": 0.2}).reasons[0][:38]
    "the U-Net ensemble's nets disagree on "
    >>> review_segmentation({"uncertain_ratio": float("inf"), "mean_probability": float("nan"),
    ...                      "outside_ratio": 0.0}).reasons[0][:60]
    'uncertain tumour edge and no lesion kept, check the overlay '
    """
    lim = dict(REVIEW_LIMITS[review_kind(figures)])
    lim.update(limits or {})
    unknown = sorted(set(lim) - set(REVIEW_CHECKS))
    if unknown:
        raise InputError(f"no review check for {unknown}: expected among {sorted(REVIEW_CHECKS)}")
    reasons, excess = [], [0.0]
    for name, (side, text) in REVIEW_CHECKS.items():
        if name not in lim or name not in figures:
            continue
        v, limit = float(figures[name]), float(lim[name])
        if np.isnan(v):
            continue
        if side == "above":
            beyond = v > limit
            excess.append(v / max(limit, 1e-6) if np.isfinite(v) else 10.0)
        else:
            beyond = v < limit
            excess.append((1.0 - v) / max(1.0 - limit, 1e-6) if np.isfinite(v) else 10.0)
        if beyond:
            if np.isinf(v) and name in EMPTY_LESION_REASONS:
                text = EMPTY_LESION_REASONS[name]
            reasons.append(_reason(text, v, limit))
    score = float(np.clip(1.0 - 0.5 * max(excess), 0.0, 1.0))
    return Review(bool(reasons), tuple(reasons), score, dict(figures))


_FIGURE_SPEC = re.compile(r"\{(v|lim):\.(\d)([f%])\}")


def _reason(text: str, v: float, limit: float) -> str:
    """A check's reason with its figure and limit.

    Both get more decimals (up to 3 more) while the figure would read as its
    limit: "0.20 (limit 0.20)" for 0.203 over 0.2.

    >>> _reason("ratio {v:.2f} (limit {lim:.2f})", 0.203, 0.2)
    'ratio 0.203 (limit 0.200)'
    >>> _reason("ratio {v:.2f} (limit {lim:.2f})", 0.31, 0.2)
    'ratio 0.31 (limit 0.20)'
    """

    def widen(extra: int) -> str:
        return _FIGURE_SPEC.sub(lambda m: f"{{{m[1]}:.{int(m[2]) + extra}{m[3]}}}", text)

    for extra in range(4):
        widened = widen(extra)
        spec = next((f".{m[2]}{m[3]}" for m in _FIGURE_SPEC.finditer(widened) if m[1] == "v"), None)
        if spec is None or not np.isfinite(v) or format(v, spec) != format(limit, spec):
            break
    return widened.format(v=v, lim=limit)
