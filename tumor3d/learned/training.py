"""Training rows and the booster that turns them into a :class:`ForestModel`.

Sampling follows the BraTS 2013 forests (Zikic et al. 2012): every
patient contributes about the same number of rows whatever its size, from
three pools: the lesion, the tissue far from it, and a band around it
(where the boundary is decided). Rows are weighted so that each pool and
each patient count the same in the loss. LightGBM is imported only here,
lazily (``pip install tumor3d[train]``); inference does not need it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage as ndi

from tumor3d.errors import InputError
from tumor3d.learned.features import FEATURE_NAMES, PatientFeatures
from tumor3d.learned.forest import ForestModel, forest_from_lightgbm_dump

__all__ = ["TrainingRows", "TRAIN_PARAMS", "sample_rows", "train_forest"]

#: LightGBM parameters of the shipped model (``reports/model_card.md`` gives the
#: cross-validation that chose them).
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
    return TrainingRows(features.values[sel], y_all[sel].astype(np.uint8), np.concatenate(weights))


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
    names = list(FEATURE_NAMES) if rows.x.shape[1] == len(FEATURE_NAMES) else None
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
