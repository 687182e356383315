"""benchmarks/learned_cv.py's training: the scored cut is never trained on unless asked
(``--eval-offset``), and ``--forest-seed`` reseeds the rows and the trees."""

from __future__ import annotations

import argparse

import numpy as np
import pytest
from benchmark_scripts import benchmark_module

learned_cv = benchmark_module("learned_cv")


def _case(offset: int, native: bool = False):
    """A 1 mm volume whose every thin slice holds its own index: a slab's value names its cut."""
    raw = np.broadcast_to(np.arange(40, dtype=np.float32)[:, None, None], (40, 4, 4)).copy()
    image = raw if native else learned_cv.emulate_thick(raw, offset).astype(np.float32)
    spec = learned_cv.CaseSpec("p/flair", "p", "s", "lgg" if native else "brats_flair",
                               "", "", "flair", native=native)  # fmt: skip
    return learned_cv.Prepared(
        spec, image, np.zeros(image.shape, bool), np.zeros(raw.shape, bool),
        np.ones(image.shape, bool), (5.0, 1.0, 1.0), (1.0, 1.0), 1.0, None, None,
        None if native else raw, None, learned_cv.OFFSET if native else offset,
    )  # fmt: skip


@pytest.fixture
def trained_cuts(monkeypatch):
    """The first slab value of every image the training rows were sampled from."""
    seen: list[float] = []
    monkeypatch.setattr(learned_cv, "_features", lambda p: p.image)
    monkeypatch.setattr(
        learned_cv, "sample_rows", lambda feats, ref, rng: seen.append(float(feats[0, 0, 0]))
    )
    monkeypatch.setattr(learned_cv.TrainingRows, "concatenate", staticmethod(list))
    return seen


@pytest.fixture
def sampling_draws(monkeypatch):
    """The first draw of the generator each patient's rows were sampled with."""
    seen: list[float] = []
    monkeypatch.setattr(learned_cv, "_features", lambda p: p.image)
    monkeypatch.setattr(learned_cv, "sample_rows", lambda f, ref, rng: seen.append(rng.random()))
    monkeypatch.setattr(learned_cv.TrainingRows, "concatenate", staticmethod(list))
    return seen


@pytest.mark.parametrize(
    ("scored", "train", "expected"),
    [
        (2, [2], [2.5]),  # as shipped: the scored cut is the training cut
        (0, [2], [2.5]),  # another cut scored: still trained on offset 2 only, not on 0
        (4, [2], [2.5]),
        (0, [0, 2], [0.5, 2.5]),  # asked for: its own rows, then offset 2
        (2, [1, 3], [2.5, 1.5, 3.5]),  # the default cut's own rows always (as before)
    ],
)
def test_the_models_train_on_the_training_offsets_whatever_cut_is_scored(
    trained_cuts, scored, train, expected
):
    args = argparse.Namespace(train_offsets=train)
    learned_cv._training_rows([_case(scored)], args, cfg=None)
    assert trained_cuts == expected


def test_a_native_case_trains_on_its_own_slices_whatever_the_offsets(trained_cuts):
    learned_cv._training_rows([_case(0, native=True)], argparse.Namespace(train_offsets=[0]), None)
    assert trained_cuts == [0.0]


@pytest.mark.parametrize(("seed", "rng_seed", "params"), [(None, 0, None), (1, 1, {"seed": 1})])
def test_a_forest_seed_reseeds_the_rows_and_lightgbm_and_none_keeps_the_shipped_training(
    sampling_draws, seed, rng_seed, params
):
    args = argparse.Namespace(train_offsets=[2], forest_seed=seed)
    learned_cv._training_rows([_case(2, native=True)], args, None)
    assert sampling_draws == [np.random.default_rng(rng_seed).random()]
    assert learned_cv._forest_params(args) == params
