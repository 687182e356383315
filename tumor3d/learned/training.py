"""Training rows and the booster that turns them into a :class:`ForestModel`.

Sampling follows the BraTS 2013 forests (Zikic et al. 2012): every
patient contributes about the same number of rows whatever its size, from
three pools: the lesion, the tissue far from it, and a band around it
(where the boundary is decided). Rows are weighted so that each pool and
each patient count the same in the loss. LightGBM is imported only here,
lazily (``pip install tumor3d[train]``); inference does not need it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage as ndi

from tumor3d.errors import InputError
from tumor3d.learned.context import CONTEXT_NAMES
from tumor3d.learned.features import FEATURE_NAMES, PatientFeatures
from tumor3d.learned.forest import ForestModel, forest_from_lightgbm_dump

__all__ = [
    "TrainingRows",
    "TRAIN_PARAMS",
    "sample_indices",
    "sample_rows",
    "train_auto_context",
    "train_forest",
]

#: LightGBM parameters of the shipped models. Set once; for the FLAIR + T2 forest a nested
#: cross-validation by patient against three other settings (deeper, longer, shallower
#: trees) kept them (``reports/learned_cv.md``, "The forest's LightGBM parameters,
#: nested"); the T1c forest uses the same, not cross-validated on their own.
TRAIN_PARAMS: dict[str, Any] = {
    "objective": "binary",
    "learning_rate": 0.08,
    "num_leaves": 31,
    "min_data_in_leaf": 200,
    "feature_fraction": 0.8,
    "bagging_fraction": 0.7,
    "bagging_freq": 1,
    "lambda_l2": 1.0,
    "num_threads": 2,
    "verbose": -1,
    "seed": 0,
    "deterministic": True,
    "force_row_wise": True,
}
NUM_ROUNDS = 150


@dataclass(frozen=True)
class TrainingRows:
    """Feature rows with their labels and weights."""

    x: np.ndarray  # (n, n_features) float32
    y: np.ndarray  # (n,) uint8
    w: np.ndarray  # (n,) float32

    @staticmethod
    def concatenate(parts: list[TrainingRows]) -> TrainingRows:
        """The rows of every part, in order."""
        if not parts:
            raise InputError("no training rows")
        return TrainingRows(
            np.concatenate([p.x for p in parts]),
            np.concatenate([p.y for p in parts]),
            np.concatenate([p.w for p in parts]),
        )


def sample_indices(
    features: PatientFeatures,
    label: np.ndarray,
    *,
    rng: np.random.Generator,
    n_lesion: int = 6000,
    n_far: int = 6000,
    n_band: int = 4000,
    band_px: int = 8,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rows :func:`sample_rows` takes: ``(row numbers, labels, weights)``.

    The row numbers index ``features.values`` (and ``features.index``), so
    other columns of the same pixels (auto-context) can be added to them.
    """
    lab = np.asarray(label, dtype=bool)
    if lab.shape != features.shape:
        raise InputError(f"label shape {lab.shape} does not match features {features.shape}")
    y_all = lab.ravel()[features.index]
    near = ndi.binary_dilation(lab, structure=np.ones((1, 3, 3), bool), iterations=band_px)
    near_all = near.ravel()[features.index]
    pools = [
        (np.flatnonzero(y_all), n_lesion),
        (np.flatnonzero(~near_all), n_far),
        (np.flatnonzero(near_all & ~y_all), n_band),
    ]
    total = float(sum(n for idx, n in pools if idx.size))
    rows, weights = [], []
    for idx, n in pools:
        if idx.size == 0:
            continue
        take = rng.choice(idx, size=min(n, idx.size), replace=False)
        rows.append(take)
        weights.append(np.full(take.size, (n / total) / take.size * 1000.0, np.float32))
    if not rows:
        raise InputError("the patient has no candidate pixel")
    sel = np.concatenate(rows)
    return sel, y_all[sel].astype(np.uint8), np.concatenate(weights)


def sample_rows(
    features: PatientFeatures,
    label: np.ndarray,
    *,
    rng: np.random.Generator,
    n_lesion: int = 6000,
    n_far: int = 6000,
    n_band: int = 4000,
    band_px: int = 8,
) -> TrainingRows:
    """Rows of one patient: lesion, far tissue and the band around the lesion.

    Each pool is sampled without replacement up to its size; its rows are
    weighted so that the pool weighs ``n_pool / n_total`` of the patient
    even when the pool is smaller (a small lesion is not under-counted).
    A patient without lesion gives far-tissue rows only.
    """
    sel, y, w = sample_indices(
        features,
        label,
        rng=rng,
        n_lesion=n_lesion,
        n_far=n_far,
        n_band=n_band,
        band_px=band_px,
    )
    return TrainingRows(features.values[sel], y, w)


def train_forest(
    rows: TrainingRows,
    *,
    params: dict[str, Any] | None = None,
    num_rounds: int = NUM_ROUNDS,
    meta: dict[str, Any] | None = None,
) -> ForestModel:
    """Fit a LightGBM binary booster to ``rows`` and flatten it.

    Raises
    ------
    InputError
        When LightGBM is not installed (``pip install 'tumor3d[train]'``) or
        the rows hold one class only.
    """
    try:
        import lightgbm as lgb
    except ImportError:  # pragma: no cover - the test extra installs it
        raise InputError("training needs LightGBM: pip install 'tumor3d[train]'") from None
    if rows.y.min(initial=0) == rows.y.max(initial=0):
        raise InputError("training rows hold one class only: lesion and tissue are both needed")
    p = dict(TRAIN_PARAMS)
    p.update(params or {})
    if rows.x.shape[1] == len(FEATURE_NAMES):
        names: list[str] | None = list(FEATURE_NAMES)
    elif rows.x.shape[1] == len(FEATURE_NAMES) + len(CONTEXT_NAMES):
        names = list(FEATURE_NAMES) + list(CONTEXT_NAMES)
    else:
        names = None
    data = lgb.Dataset(
        rows.x, label=rows.y, weight=rows.w, feature_name=names or "auto", free_raw_data=True
    )
    booster = lgb.train(p, data, num_boost_round=int(num_rounds))
    info = {
        "feature_names": names or [f"f{i}" for i in range(rows.x.shape[1])],
        "trainer": f"lightgbm {lgb.__version__}",
        "params": p,
        "num_rounds": int(num_rounds),
    }
    info.update(meta or {})
    return forest_from_lightgbm_dump(booster.dump_model(), info)


def train_auto_context(
    cases: Sequence[tuple[PatientFeatures, np.ndarray]],
    *,
    spacing_mm: Sequence[tuple[float, float, float]],
    patients: Sequence[str] | None = None,
    folds: int = 5,
    threshold: float = 0.5,
    keep_fraction: float = 1.0,
    rng: np.random.Generator | None = None,
    params: dict[str, Any] | None = None,
    num_rounds: int = NUM_ROUNDS,
    meta: dict[str, Any] | None = None,
    sample: dict[str, int] | None = None,
) -> ForestModel:
    """Train a two-stage (auto-context) model from ``(features, reference mask)`` pairs.

    Stage 1 is :func:`train_forest` on every case's :func:`sample_rows`.
    Stage 2 is trained on the same rows with the
    :data:`~tumor3d.learned.context.CONTEXT_NAMES` columns of each case's
    *out-of-fold* stage-1 probability (``folds`` folds by patient, dealt
    round-robin in order of first appearance; a patient's sequences share a
    fold), the first-stage lesion cut at ``threshold`` / ``keep_fraction``
    as inference cuts it. The result is the stage-1 forest with the second
    stage as its ``context`` and ``threshold`` / ``keep_fraction`` in its
    ``meta``, ready for :func:`~tumor3d.learned.segment.segment_learned`.

    Parameters
    ----------
    cases : sequence of (PatientFeatures, (z, y, x) bool ndarray)
        Each case's features and its reference lesion on the same slices.
    spacing_mm : sequence of (3,) tuple of float
        Each case's ``(slice step, row, column)`` in mm.
    patients : sequence of str, optional
        Each case's patient (default: every case its own patient).
    sample : dict, optional
        Pool sizes for :func:`sample_rows` (``n_lesion``, ``n_far``, ``n_band``).

    Raises
    ------
    InputError
        Fewer than two patients, mismatched lengths, or what :func:`train_forest` raises.
    """
    from dataclasses import replace

    from tumor3d.learned.context import context_features
    from tumor3d.learned.forest import predict_proba
    from tumor3d.learned.segment import keep_main_lesion

    n = len(cases)
    pats = [str(i) for i in range(n)] if patients is None else [str(p) for p in patients]
    if len(spacing_mm) != n or len(pats) != n:
        raise InputError(f"{n} cases but {len(spacing_mm)} spacings and {len(pats)} patient names")
    order = list(dict.fromkeys(pats))
    if len(order) < 2:
        raise InputError("auto-context training needs at least two patients (out-of-fold maps)")
    k = max(2, min(int(folds), len(order)))
    fold_of = {p: i % k for i, p in enumerate(order)}
    fold = np.array([fold_of[p] for p in pats])
    rng = np.random.default_rng(0) if rng is None else rng
    picked = [sample_indices(f, lab, rng=rng, **(sample or {})) for f, lab in cases]
    rows1 = [
        TrainingRows(f.values[sel], y, w) for (f, _), (sel, y, w) in zip(cases, picked, strict=True)
    ]

    def fit(idx, parts: list[TrainingRows], m: dict[str, Any] | None = None) -> ForestModel:
        return train_forest(
            TrainingRows.concatenate([parts[i] for i in idx]),
            params=params,
            num_rounds=num_rounds,
            meta=m,
        )

    rows2: list[TrainingRows | None] = [None] * n
    for j in range(k):
        held = np.flatnonzero(fold == j)
        first = fit(np.flatnonzero(fold != j), rows1)
        for i in held:
            feats, _ = cases[i]
            sel, y, w = picked[i]
            prob = np.zeros(feats.shape, np.float32)
            prob.ravel()[feats.index] = predict_proba(first, feats.values)
            vox = float(np.prod(spacing_mm[i]))
            lesion = keep_main_lesion(
                prob,
                threshold,
                keep_fraction=keep_fraction,
                min_voxels=max(1, int(round(20.0 / vox))),
            )
            ctx = context_features(
                prob,
                lesion,
                candidates=feats.candidates,
                index=feats.index[sel],
                spacing_mm=spacing_mm[i],
            )
            rows2[i] = TrainingRows(np.hstack([feats.values[sel], ctx]), y, w)
    info = dict(meta or {})
    info.update(threshold=float(threshold), keep_fraction=float(keep_fraction))
    stage1 = fit(range(n), rows1, info)
    stage2 = fit(range(n), [r for r in rows2 if r is not None], {"stage": "auto-context"})
    return replace(stage1, context=stage2)
