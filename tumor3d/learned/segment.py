"""The learned method: per-pixel lesion probability, then one lesion in 3-D.

:func:`segment_learned` computes the features of every tissue pixel
(:mod:`tumor3d.learned.features`), the model's probability
(:mod:`tumor3d.learned.forest`), and keeps the connected 3-D region of
pixels above the model's threshold that carries the most probability, with
any other region carrying at least ``keep_fraction`` of it (a multifocal
lesion); holes are filled per slice. Given a U-Net
(:mod:`tumor3d.learned.cnn`) or an ensemble of them (the mean of the nets'),
the probability is the mean of the forest's and the network's, computed in a
thread beside the forest, before the same cut and region (as cross-validated,
``reports/learned_cv.md``). It also returns the probability volume
(per-voxel confidence, written as a NIfTI by the stage) and the figures
:func:`tumor3d.learned.review.review_segmentation` judges.
"""

from __future__ import annotations

from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage as ndi

from tumor3d.errors import InputError
from tumor3d.imaging.preprocess import fill_holes_per_slice
from tumor3d.learned.cnn import UNetWeights, as_nets, unet_member_probabilities
from tumor3d.learned.context import CONTEXT_NAMES, context_features
from tumor3d.learned.features import FEATURE_NAMES, compute_features
from tumor3d.learned.forest import ForestModel, predict_proba

__all__ = [
    "LearnedSegmentation",
    "check_model_features",
    "keep_main_lesion",
    "region_preference",
    "segment_learned",
]

_STRUCT_3D = np.ones((3, 3, 3), dtype=bool)

#: Sequences whose lesion is chosen only among the regions the prior (the robust method's
#: mask) touches: on T1c, enhancing normal structures (vessels, the choroid plexus, dura)
#: form regions of their own that can outweigh the tumour's or stand in for a tumour that
#: is not there, and the rule-based lesion model sets them aside. Where the prior found no
#: lesion, or none of the regions touches it, there is none. Out of fold the choice
#: changes no T1c case's figures, keeps pat0005's tumour with 6-10 % Rician noise, where the
#: largest region was another, and finds nothing in the tumour-free T1c brains, where the
#: largest region was 31 mL of normal enhancement (reports/learned_cv.md, "The T1c region
#: chosen where the robust method found its lesion").
PRIOR_CHOOSES_REGION = ("t1c",)


def region_preference(modality: str, prior: np.ndarray | None) -> dict[str, Any]:
    """:func:`keep_main_lesion`'s ``prefer`` and ``prefer_only``: the prior, only, on T1c.

    The sequences are :data:`PRIOR_CHOOSES_REGION` (case-insensitive); other
    sequences, or no prior given, choose among every region (an empty dict).

    >>> region_preference("FLAIR", np.ones((1, 2, 2), bool))
    {}
    >>> sorted(region_preference("T1c", np.ones((1, 2, 2), bool)))
    ['prefer', 'prefer_only']
    """
    if prior is None or modality.strip().lower() not in PRIOR_CHOOSES_REGION:
        return {}
    return {"prefer": prior, "prefer_only": True}


@dataclass(frozen=True)
class LearnedSegmentation:
    """Result of :func:`segment_learned`.

    Attributes
    ----------
    mask : (z, y, x) ndarray of bool
        The lesion.
    probability : (z, y, x) ndarray of float32
        The model's lesion probability (the forest's is 0 outside the tissue);
        with a U-Net, the mean of the forest's and the network's.
    threshold : float
        The probability cut that made ``mask``.
    forest_probability, cnn_probability : (z, y, x) ndarray of float32 or None
        With a U-Net: the two probabilities that were averaged (None without);
        the review judges their disagreement inside the lesion
        (:func:`tumor3d.learned.review.review_features`, ``model_disagreement``).
    cnn_members : (n_nets, z, y, x) ndarray of float32 or None
        With a U-Net: each net's probability (``cnn_probability`` is their
        mean); the review judges an ensemble's spread inside the lesion
        (``net_spread``).
    """

    mask: np.ndarray
    probability: np.ndarray
    threshold: float
    forest_probability: np.ndarray | None = None
    cnn_probability: np.ndarray | None = None
    cnn_members: np.ndarray | None = None


def keep_main_lesion(
    probability: np.ndarray,
    threshold: float,
    *,
    keep_fraction: float = 0.3,
    min_voxels: int = 20,
    prefer: np.ndarray | None = None,
    prefer_only: bool = False,
) -> np.ndarray:
    """The 3-D region above ``threshold`` with the largest summed probability, and its peers.

    Regions are 26-connected; any other region whose summed probability is
    at least ``keep_fraction`` of the largest is kept too. Regions under
    ``min_voxels`` voxels are dropped. Holes are filled per slice. With
    ``prefer`` (a bool mask of the same shape), the choice is among the regions
    that overlap it, when any of them is large enough; otherwise as without it,
    or, with ``prefer_only``, no lesion.

    Examples
    --------
    >>> p = np.zeros((1, 12, 12), np.float32); p[0, 1:5, 1:5] = 0.9; p[0, 8:10, 8:10] = 0.6
    >>> int(keep_main_lesion(p, 0.5, min_voxels=1).sum())
    16
    >>> prior = np.zeros(p.shape, bool); prior[0, 9, 9] = True
    >>> int(keep_main_lesion(p, 0.5, min_voxels=1, keep_fraction=1.0, prefer=prior).sum())
    4
    >>> elsewhere = np.zeros(p.shape, bool); elsewhere[0, 11, 0] = True
    >>> int(keep_main_lesion(p, 0.5, min_voxels=1, prefer=elsewhere).sum())
    16
    >>> int(keep_main_lesion(p, 0.5, min_voxels=1, prefer=elsewhere, prefer_only=True).sum())
    0
    """
    prob = np.asarray(probability, dtype=np.float32)
    if prob.ndim != 3:
        raise InputError(f"probability must be 3-D (z, y, x), got shape {prob.shape}")
    if not 0.0 < float(threshold) < 1.0:
        raise InputError(f"threshold must lie in (0, 1), got {threshold}")
    if not 0.0 <= float(keep_fraction) <= 1.0:
        raise InputError(f"keep_fraction must lie in [0, 1], got {keep_fraction}")
    above = prob > float(threshold)
    labels, n = ndi.label(above, structure=_STRUCT_3D)
    if n == 0:
        return above
    ids = np.arange(1, n + 1)
    mass = ndi.sum_labels(prob, labels, ids)
    size = ndi.sum_labels(above, labels, ids)
    mass = np.where(size >= int(min_voxels), mass, 0.0)
    if prefer is not None:
        prefer = np.asarray(prefer, dtype=bool)
        if prefer.shape != prob.shape:
            raise InputError(f"prefer has shape {prefer.shape}, the probability {prob.shape}")
        touching = ndi.sum_labels(prefer, labels, ids) > 0
        if prefer_only or (mass * touching).max() > 0:
            mass = mass * touching
    if mass.max() <= 0:
        return np.zeros_like(above)
    keep = ids[mass >= float(keep_fraction) * mass.max()]
    return fill_holes_per_slice(np.isin(labels, keep))


def check_model_features(model: ForestModel, *, source: str | None = None) -> None:
    """Refuse a forest trained on other features than this version of tumor3d computes.

    By the names its metadata records, where it records them, and by the columns its
    trees read (each stage: the features, and the second stage's context features
    beside them). ``source`` (a file) starts the message.
    """
    where = f"{source}: " if source else ""
    stages = [(model, FEATURE_NAMES)]
    if model.context is not None:
        stages.append((model.context, FEATURE_NAMES + CONTEXT_NAMES))
    for stage, expected in stages:
        names = stage.meta.get("feature_names")
        top = int(stage.feature.max(initial=-1))
        if (names and tuple(names) != expected) or top >= len(expected):
            raise InputError(
                f"{where}the model was trained on other features than this version of "
                f"tumor3d computes ({len(expected)}; its trees read column {top}); retrain it "
                "(tumor3d train)"
            )


def segment_learned(
    image: np.ndarray,
    *,
    model: ForestModel,
    spacing_mm: tuple[float, float, float],
    modality: str,
    lr_axis: int | None = 2,
    threshold: float | None = None,
    keep_fraction: float | None = None,
    prior: np.ndarray | None = None,
    cnn: UNetWeights | Sequence[UNetWeights] | None = None,
) -> LearnedSegmentation:
    """Segment one patient's lesion with a trained forest.

    Parameters
    ----------
    image : (z, y, x) ndarray of real numbers
        The slices as acquired. Not modified.
    model : ForestModel
        Trained on :data:`~tumor3d.learned.features.FEATURE_NAMES`; with a
        ``context`` stage (auto-context), that stage's probability is the answer.
    spacing_mm : (3,) tuple of float
        ``(slice step, row, column)`` in mm.
    modality : {"flair", "t2", "t1c"}
    lr_axis : {1, 2} or None
        Left-right array axis (:func:`tumor3d.segmentation.lesion.left_right_axis`).
    threshold, keep_fraction : float, optional
        Override the model's own (``model.meta``; defaults 0.5 and 0.3).
    prior : (z, y, x) ndarray of bool, optional
        The rule-based lesion of the same slices (the robust method's mask),
        a feature of the model (:func:`~tumor3d.learned.features.compute_features`).
    cnn : UNetWeights or sequence of UNetWeights, optional
        A U-Net, or an ensemble of them (:func:`tumor3d.learned.shipped.shipped_cnn`):
        the probability becomes the mean of the forest's and the network's
        (an ensemble's: the mean of its nets',
        :func:`~tumor3d.learned.cnn.unet_member_probabilities`, computed in a
        thread beside the features and the forest), cut and kept as the
        forest's alone would be. None: the forest alone.

    Returns
    -------
    LearnedSegmentation
    """
    if not isinstance(model, ForestModel):
        raise InputError(f"model must be a ForestModel, got {type(model).__name__}")
    check_model_features(model)
    nets = None if cnn is None else as_nets(cnn, name="cnn")
    args = (image, model, spacing_mm, modality, lr_axis, threshold, keep_fraction, prior)
    p_cnn = members = None
    if nets is None:
        forest = _forest(*args)
        prob = forest.probability
    else:
        # the network holds the GIL little (matrix products, numpy): it runs beside the forest
        with ThreadPoolExecutor(1, thread_name_prefix="tumor3d-unet") as pool:
            pixel_mm = (float(spacing_mm[1]), float(spacing_mm[2]))  # a net framed in mm
            net = pool.submit(unet_member_probabilities, nets, image, pixel_mm=pixel_mm)
            forest = _forest(*args)
            members = net.result()
        p_cnn = members.mean(axis=0, dtype=np.float32)
        prob = (0.5 * (forest.probability + p_cnn)).astype(np.float32)
    # T1c: only among the regions the rule-based lesion (the prior) touches
    mask = keep_main_lesion(
        prob,
        forest.threshold,
        keep_fraction=forest.keep_fraction,
        min_voxels=forest.min_voxels,
        **region_preference(modality, prior),
    )
    both = p_cnn is not None
    return LearnedSegmentation(
        mask, prob, forest.threshold, forest.probability if both else None, p_cnn, members
    )


@dataclass(frozen=True)
class _Forest:
    """The forest's probability, its cut, keep fraction and least region (voxels)."""

    probability: np.ndarray
    threshold: float
    keep_fraction: float
    min_voxels: int


def _forest(
    image: np.ndarray,
    model: ForestModel,
    spacing_mm: tuple[float, float, float],
    modality: str,
    lr_axis: int | None,
    threshold: float | None,
    keep_fraction: float | None,
    prior: np.ndarray | None,
) -> _Forest:
    """The forest's probability (both stages, auto-context), cut, keep fraction, least region."""
    t_model = float(model.meta.get("threshold", 0.5))
    kf_model = float(model.meta.get("keep_fraction", 0.3))
    t = t_model if threshold is None else float(threshold)
    kf = kf_model if keep_fraction is None else float(keep_fraction)
    feats = compute_features(
        image, spacing_mm=spacing_mm, modality=modality, lr_axis=lr_axis, prior=prior
    )
    # a lesion of less than ~20 mm3 is noise at any slice thickness
    voxel_mm3 = float(np.prod(spacing_mm))
    min_voxels = max(1, int(round(20.0 / voxel_mm3)))
    prob = np.zeros(feats.shape, dtype=np.float32)
    prob.ravel()[feats.index] = predict_proba(model, feats.values)
    if model.context is not None:
        # auto-context: the first stage's lesion at the model's own cut, as in training
        first = keep_main_lesion(prob, t_model, keep_fraction=kf_model, min_voxels=min_voxels)
        ctx = context_features(
            prob, first, candidates=feats.candidates, index=feats.index, spacing_mm=spacing_mm
        )
        prob = np.zeros(feats.shape, dtype=np.float32)
        prob.ravel()[feats.index] = predict_proba(model.context, np.hstack([feats.values, ctx]))
    return _Forest(prob, t, kf, min_voxels)
