"""The review's bagged choice of limits (benchmarks/review_cv.py --bagged)."""

from __future__ import annotations

import itertools
from collections import Counter

import numpy as np
import pytest
from benchmark_scripts import benchmark_module

review_cv = benchmark_module("review_cv")


def _rows(n: int) -> list[dict]:
    return [{"case": f"Brats18_{i}/{s}"} for i in range(n) for s in ("flair", "t2", "t1c")]


def test_a_case_belongs_to_its_patient_whatever_the_sequence():
    assert review_cv.patient("Brats18_TCIA01_378_1/t2") == "Brats18_TCIA01_378_1"
    assert review_cv.patient("phantom/1003/flair") == "phantom/1003"
    assert review_cv.patient("lgg/TCGA_CS_4942_19970222") == "lgg/TCGA_CS_4942_19970222"
    assert review_cv.patient("brain2/t1c") == "brain2"


def test_bagging_draws_each_patient_whole_in_every_set_and_takes_the_median():
    grid = review_cv.GRID["net_spread"]
    calls = itertools.count()
    drawn = []

    def pick(a, b):
        pa = Counter(review_cv.patient(r["case"]) for r in a)
        pb = Counter(review_cv.patient(r["case"]) for r in b)
        assert all(v % 3 == 0 for v in pa.values())  # all three sequences of a drawn patient
        assert {p: v // 3 for p, v in pa.items()} == pb  # the same draw in both sets
        drawn.append(len(pa))
        k = (0, 0, 5)[next(calls) % 3]  # grid indices 0, 0, 5, 0, 0, 5, ...: 8 x 0, 3 x 5
        return {"net_spread": grid[k]}, {"net_spread": grid[5 - k]}

    second = [{"case": f"Brats18_{i}"} for i in range(9)]
    net, alone = review_cv.bagged(pick, [_rows(9), second], 11)
    # the median index (0; 5 for the second), not the mean (1.4 or 3.6, whichever rounding)
    assert net == {"net_spread": grid[0]} and alone == {"net_spread": grid[5]}
    assert len(drawn) == 11 and min(drawn) < 9  # resampled with replacement


def test_bagging_one_choice_of_several_figures_takes_each_figures_median():
    grid_p, grid_s = review_cv.GRID["mean_probability"], review_cv.GRID["net_spread"]
    picks = iter([(0, 5), (4, 5), (4, 1), (5, 1), (4, 0)])  # medians: 4 and 1

    def pick(rows):
        i, j = next(picks)
        return {"mean_probability": grid_p[i], "net_spread": grid_s[j]}

    chosen = review_cv.bagged(pick, [_rows(4)], 5)
    assert chosen == {"mean_probability": grid_p[4], "net_spread": grid_s[1]}


def _judged_rows(n: int, seed: int) -> list[dict]:
    rng = np.random.default_rng(seed)
    return [
        {
            "case": f"Brats18_{i}/flair", "fold": i % 2, "group": "brats_flair",
            "vol_err": float(rng.choice([-40.0, 5.0, 15.0])), "est_ml": 10.0, "doubts": [],
            "mean_probability": float(rng.uniform(0.6, 0.95)),
            "outside_ratio": float(rng.uniform(0.0, 0.5)),
            "net_spread": float(rng.uniform(0.0, 0.3)),
            "uncertain_ratio": float(rng.uniform(0.2, 3.0)),
        }
        for i in range(n)
    ]  # fmt: skip


def test_the_bagged_choice_is_made_for_every_fold_and_the_final_limits(monkeypatch):
    rows, alone = _judged_rows(16, 1), _judged_rows(16, 2)
    for r in alone:
        r["net_spread"] = None  # the forest alone: no ensemble
    calls = []
    real = review_cv.bagged

    def spy(pick, row_sets, n_boot, seed=0):
        calls.append((n_boot, sum(len(r) for r in row_sets)))
        return real(pick, row_sets, n_boot, seed)

    monkeypatch.setattr(review_cv, "bagged", spy)
    plain = review_cv.cross_validate_split(rows, alone)
    assert calls == []  # bag 0: the single choice, as before
    bag = review_cv.cross_validate_split(rows, alone, bag=3)
    # one bagged choice per fold (its 8 + 8 choosing rows) and one on every row
    assert calls == [(3, 16), (3, 16), (3, 32)]
    assert set(bag) == set(plain) and all(len(v) == 2 for v in bag["fold_limits"].values())


def test_bagging_needs_an_odd_number_of_resamples():
    with pytest.raises(ValueError, match="odd"):
        review_cv.bagged(lambda rs: {}, [_rows(3)], 10)
