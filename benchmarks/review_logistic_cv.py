"""A learned review score, nested by patient: does a combination of the figures flag more?

The shipped review judges each figure against a limit of its own (``review_cv.py``).
This script asks whether a learned combination of the same figures does better: a
logistic score of them (standardised, ridge weight ``--ridge``) fitted fold by fold on the
other folds' cases (volume off by more than 25 % against within 10 %), its cut chosen on
those folds as the highest share of bad cases flagged while at most 25 % of their real
within-10 % cases are (the review's rule), then judged on the held-out fold. The run's
other doubts (``review_doubts.py``'s ``doubts``: caveats, an empty result) flag as in the
shipped status.

Reads the rows of ``review_doubts.py --out`` (out of fold: every case was segmented by
models that never saw its patient).

Usage::

    python benchmarks/review_logistic_cv.py learned_doubts.json
    python benchmarks/review_logistic_cv.py learned_doubts.json --ridge 0.1 1 10
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

#: The figures the score combines (each row's, as ``review_doubts.py`` writes them).
FEATURES = (
    "1 - mean probability",
    "log(1 + outside ratio)",
    "log(1 + uncertain ratio)",
    "net spread (0 without nets)",
    "model disagreement (0 without a net)",
    "a net ran",
    "log volume (mL)",
    "1 - prior agreement",
)


def _finite(value, default: float, top: float = math.inf) -> float:
    if value is None or not math.isfinite(float(value)):
        return default
    return min(float(value), top)


def features(row: dict) -> list[float]:
    """The :data:`FEATURES` of one row (an empty lesion: no probability, ratios at 10)."""
    spread = _finite(row.get("net_spread"), math.nan)
    has_net = math.isfinite(spread)
    return [
        1.0 - _finite(row.get("mean_probability"), 0.0),
        math.log1p(_finite(row.get("outside_ratio"), 10.0, 10.0)),
        math.log1p(_finite(row.get("uncertain_ratio"), 10.0, 10.0)),
        spread if has_net else 0.0,
        _finite(row.get("model_disagreement"), 0.0),
        float(has_net),
        math.log(max(_finite(row.get("volume_ml"), 0.0), 1e-3)),
        1.0 - _finite(row.get("prior_agreement"), 0.0),
    ]


def fit_logistic(x: np.ndarray, y: np.ndarray, ridge: float, steps: int = 3000):
    """A ridge-penalised logistic regression by gradient descent; returns the scorer."""
    mu, sd = x.mean(0), x.std(0) + 1e-9
    z = (x - mu) / sd
    w, b = np.zeros(z.shape[1]), 0.0
    for _ in range(steps):
        p = 1.0 / (1.0 + np.exp(-(z @ w + b)))
        w -= 0.5 * (z.T @ (p - y) + ridge * w) / len(y)
        b -= 0.5 * float((p - y).mean())
    return lambda xn: 1.0 / (1.0 + np.exp(-(((xn - mu) / sd) @ w + b)))


def choose_cut(score: np.ndarray, bad: np.ndarray, good_real: np.ndarray, doubt: np.ndarray):
    """The cut that flags most bad cases while at most 25 % of the real within-10 % ones.

    Doubts flag too; among cuts that flag as many bad cases, the highest (fewer flags),
    as ``review_cv.py`` chooses limits.
    """
    best, recall = math.inf, -1.0
    for cut in np.sort(np.unique(score))[::-1]:
        flagged = (score >= cut) | doubt
        if good_real.any() and flagged[good_real].mean() > 0.25:
            break
        now = float(flagged[bad].mean()) if bad.any() else 0.0
        if now > recall:
            best, recall = cut, now
    return best


def nested(rows: Sequence[dict], ridge: float) -> np.ndarray:
    """Held-out flags of every row: fitted and cut on the other folds."""
    x = np.array([features(r) for r in rows])
    err = np.array([abs(float(r["vol_err"])) for r in rows])
    fold = np.array([r["fold"] for r in rows])
    doubt = np.array([bool(r.get("doubts")) for r in rows])
    real = np.array([r["group"] != "phantom" for r in rows])
    bad, good = err > 25.0, err <= 10.0
    flags = np.zeros(len(rows), bool)
    for k in np.unique(fold):
        train, test = fold != k, fold == k
        use = train & (bad | good)
        score = fit_logistic(x[use], bad[use].astype(float), ridge)
        cut = choose_cut(score(x[train]), bad[train], (good & real)[train], doubt[train])
        flags[test] = (score(x[test]) >= cut) | doubt[test]
    return flags


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rows", type=Path, help="review_doubts.py's rows (JSON)")
    ap.add_argument("--ridge", type=float, nargs="+", default=[0.1, 1.0, 10.0])
    args = ap.parse_args(argv)
    rows = json.loads(args.rows.read_text())
    err = np.array([abs(float(r["vol_err"])) for r in rows])
    real = np.array([r["group"] != "phantom" for r in rows])
    bad, good = (err > 25.0) & real, (err <= 10.0) & real
    print("| ridge | > 25 % flagged (real) | within 10 % flagged (real) |")
    print("|---|---|---|")
    for ridge in args.ridge:
        flags = nested(rows, ridge)
        print(
            f"| {ridge:g} | {flags[bad].mean():.0%} of {bad.sum()} | "
            f"{flags[good].mean():.0%} of {good.sum()} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
