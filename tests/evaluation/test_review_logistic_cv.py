"""``benchmarks/review_logistic_cv.py``: the nested logistic review on synthetic rows.

The independent expectation: where one figure separates the bad volumes from the good
ones, the held-out score flags the bad ones and keeps to the 25 % rule on the good
ones; where the figures carry nothing, it tells them apart no better than chance.
"""

from __future__ import annotations

import numpy as np
from benchmark_scripts import benchmark_module

lcv = benchmark_module("review_logistic_cv")


def _rows(rng, informative: bool) -> list[dict]:
    rows = []
    for i in range(100):
        bad = i % 2 == 0
        mean_p = (0.55 if bad else 0.93) if informative else 0.8
        rows.append(
            {
                "group": "lgg",
                "fold": i % 5,
                "vol_err": (60.0 if bad else 3.0) * (1 if i % 4 else -1),
                "mean_probability": mean_p + rng.normal(0, 0.03),
                "outside_ratio": abs(rng.normal(0, 0.05)),
                "uncertain_ratio": abs(rng.normal(0.8, 0.2)),
                "net_spread": abs(rng.normal(0.08, 0.02)),
                "model_disagreement": abs(rng.normal(0.05, 0.02)),
                "volume_ml": float(rng.uniform(5, 60)),
                "prior_agreement": float(rng.uniform(0.5, 0.95)),
                "doubts": [],
            }
        )
    return rows


def test_a_separating_figure_is_learned_and_the_cut_keeps_the_25_percent_rule():
    rows = _rows(np.random.default_rng(0), informative=True)
    flags = lcv.nested(rows, ridge=1.0)
    bad = np.array([abs(r["vol_err"]) > 25 for r in rows])
    assert flags[bad].mean() >= 0.9
    assert flags[~bad].mean() <= 0.25


def test_figures_that_carry_nothing_tell_the_bad_cases_no_better_than_chance():
    """Held out, the noise the fit learned flags bad and good cases alike (the 25 % rule
    holds on the folds that chose the cut, not beyond them: why it is nested)."""
    rows = _rows(np.random.default_rng(1), informative=False)
    flags = lcv.nested(rows, ridge=1.0)
    bad = np.array([abs(r["vol_err"]) > 25 for r in rows])
    assert abs(flags[bad].mean() - flags[~bad].mean()) <= 0.15
