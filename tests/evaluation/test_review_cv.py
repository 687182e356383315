"""The review's bagged choice of limits (benchmarks/review_cv.py --bagged)."""

from __future__ import annotations

import importlib.util
import itertools
from collections import Counter
from pathlib import Path

import pytest

_PATH = Path(__file__).resolve().parents[2] / "benchmarks" / "review_cv.py"
_SPEC = importlib.util.spec_from_file_location("review_cv_under_test", _PATH)
review_cv = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(review_cv)


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
        k = next(calls) % 3  # chosen grid indices 0, 1, 2, 0, 1, ...: 4 x 0, 4 x 1, 3 x 2
        return {"net_spread": grid[k]}, {"net_spread": grid[5 - k]}

    second = [{"case": f"Brats18_{i}"} for i in range(9)]
    net, alone = review_cv.bagged(pick, [_rows(9), second], 11)
    assert net == {"net_spread": grid[1]} and alone == {"net_spread": grid[4]}
    assert len(drawn) == 11 and min(drawn) < 9  # resampled with replacement


def test_bagging_needs_an_odd_number_of_resamples():
    with pytest.raises(ValueError, match="odd"):
        review_cv.bagged(lambda rs: {}, [_rows(3)], 10)
