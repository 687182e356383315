"""Eq. 9 has one implementation and one documented rule at a zero reference (issue 31)."""

from __future__ import annotations

import math

import pytest

import tumor3d.evaluation.metrics as ev
import tumor3d.metrics as core
from tumor3d.errors import InputError


@pytest.mark.parametrize(("est", "ref"), [(3841, 3785), (1764, 1805), (0, 10), (5, 5)])
def test_the_evaluation_and_the_core_agree(est, ref):
    expected = abs(est - ref) / ref * 100.0  # the paper's formula, written out
    assert core.relative_error_percent(est, ref) == pytest.approx(expected)
    assert ev.relative_error_percent(est, ref) == pytest.approx(expected)


def test_a_zero_reference_is_refused_or_nan_as_asked(monkeypatch):
    with pytest.raises(InputError):
        core.relative_error_percent(3, 0)
    assert math.isnan(core.relative_error_percent(3, 0, zero_truth="nan"))
    assert math.isnan(ev.relative_error_percent(3, 0))  # a tumour-free case in the evaluation
    calls = []
    real = core.relative_error_percent
    monkeypatch.setattr(
        core, "relative_error_percent", lambda *a, **k: calls.append(a) or real(*a, **k)
    )
    ev.relative_error_percent(2, 4)
    assert calls == [(2.0, 4.0)]  # the evaluation delegates: one Eq. 9
