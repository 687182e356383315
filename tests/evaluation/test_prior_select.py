"""benchmarks/prior_select.py: the robust mask's second say in the cut, and its nested choice
kept apart per family (the FLAIR choice never scores T2 rows, nor the T2 one FLAIR rows)."""

from __future__ import annotations

import numpy as np
import pytest
from benchmark_scripts import benchmark_module

prior_select = benchmark_module("prior_select")


@pytest.mark.parametrize("setting", ["or 0.3", "or 0.4", "blend 0.15", "blend 0.3", "blend 0.5"])
def test_second_say_cuts_where_the_rule_says(setting):
    rng = np.random.default_rng(3)
    m = rng.random((4, 9, 9)).astype(np.float32)
    prior = rng.random((4, 9, 9)) < 0.4
    kind, v = setting.split()
    v = float(v)
    if kind == "or":  # above 0.5, or inside the robust mask and above v
        expected = (m > 0.5) | (prior & (m > v))
    else:  # (1 - v) m + v prior > 0.5, solved for m on each side of the mask
        expected = np.where(prior, m > (0.5 - v) / (1 - v), m > 0.5 / (1 - v))
    margin = np.abs(prior_select.second_say(m, prior, setting) - 0.5) > 1e-6  # float ties
    got = prior_select.second_say(m, prior, setting) > 0.5
    np.testing.assert_array_equal(got[margin], expected[margin])
    assert margin.mean() > 0.95
    shipped = prior_select.second_say(m, prior, "shipped") > 0.5
    np.testing.assert_array_equal(shipped, m > 0.5)


def _row(fold, group, dice):
    return {"case": f"{group}/{fold}", "fold": fold, "group": group, "dice3d": dice,
            "slice_dice": dice, "vol_err": 0.0, "recall": 1.0, "spec": 1.0}  # fmt: skip


def test_each_family_is_chosen_on_its_own_rows():
    """FLAIR's 'or 0.3' wins on BraTS FLAIR and LGG; T2's 'blend 0.3' wins on T2 only: a
    choice that mixed the families (or scored T2 by the FLAIR objective) would differ."""
    folds = [0, 1]
    by_set = {}
    for s in prior_select.FLAIR_SETTINGS:
        d = 0.9 if s == "or 0.3" else 0.5
        by_set[f"flair: {s}"] = [_row(k, g, d) for k in folds for g in ("brats_flair", "lgg")]
    for s in prior_select.T2_SETTINGS:
        d = 0.8 if s == "blend 0.3" else 0.6
        by_set[f"t2: {s}"] = [_row(k, "brats_t2", d) for k in folds]
    text = prior_select.report(by_set, folds)
    flair, t2 = text.split("## t2")
    assert "| 0 | flair: or 0.3 |" in flair and "| 1 | flair: or 0.3 |" in flair
    assert "| 0 | t2: blend 0.3 |" in t2 and "| 1 | t2: blend 0.3 |" in t2
    assert "t2:" not in flair and "flair:" not in t2
    assert "| brats_t2 | nested choice | 2 | 0.800" in t2
