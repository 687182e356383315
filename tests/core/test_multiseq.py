"""Features of several co-registered sequences side by side (tumor3d.learned.multiseq).

Phantoms only: the FLAIR and T2 phantoms of one seed share the head and the
tumour (``make_phantom_patient``'s independent streams), so they are two
co-registered sequences of one patient.
"""

from __future__ import annotations

import functools

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.evaluation.metrics import dice
from tumor3d.learned.features import FEATURE_NAMES, compute_features, tissue_foreground
from tumor3d.learned.multiseq import (
    SEQUENCE_FEATURES,
    multiseq_feature_names,
    order_sequences,
    stack_features,
)
from tumor3d.phantom.patient import make_phantom_patient


@functools.cache
def _pair(seed: int, *, flair_tumour: bool = True):
    """FLAIR and T2 slices of one phantom patient and its truth (made once; read-only)."""
    t2 = make_phantom_patient(seed, modality="t2", matrix_size=(96, 96))
    fl = make_phantom_patient(seed, modality="flair", matrix_size=(96, 96), tumor=flair_tumour)
    truth = np.asarray(t2.slice_masks) > 0.5
    truth.setflags(write=False)
    return fl.scan.image, t2.scan.image, truth, t2.scan.spacing_zyx_mm


def test_one_sequence_gives_the_single_sequence_features():
    fl, _, _, sp = _pair(3)
    one = stack_features({"FLAIR": fl}, spacing_mm=sp)
    ref = compute_features(fl, spacing_mm=sp, modality="flair")
    assert np.array_equal(one.values, ref.values)
    assert np.array_equal(one.index, ref.index)


def test_a_second_sequence_adds_its_own_columns_on_the_primary_tissue():
    fl, t2, truth, sp = _pair(3)
    prior = {"t2": truth}  # any mask: it must land in the T2 block, not the FLAIR one
    both = stack_features({"t2": t2, "flair": fl}, spacing_mm=sp, priors=prior)
    names = multiseq_feature_names(["t2", "flair"])
    assert both.values.shape[1] == len(names) == len(FEATURE_NAMES) + len(SEQUENCE_FEATURES)
    # the FLAIR block is FLAIR's features unchanged
    alone = compute_features(fl, spacing_mm=sp, modality="flair")
    assert np.array_equal(both.index, alone.index)
    assert np.array_equal(both.values[:, : len(FEATURE_NAMES)], alone.values)
    # the T2 block: T2's own features at the FLAIR's tissue pixels, column by column
    cand = tissue_foreground(fl)
    t2f = compute_features(t2, spacing_mm=sp, modality="t2", prior=truth, candidates=cand)
    for n in SEQUENCE_FEATURES:
        col = names.index(f"t2.{n}")
        assert np.array_equal(both.values[:, col], t2f.values[:, FEATURE_NAMES.index(n)]), n
    inside = both.values[:, names.index("t2.prior_inside")]
    assert inside.sum() == truth.ravel()[both.index].sum() > 0
    assert both.values[:, names.index("flair.prior_inside")].sum() == 0


def test_sequence_order_does_not_depend_on_the_callers_order():
    assert order_sequences(["t1c", "T2", "flair"]) == ("flair", "t2", "t1c")
    assert order_sequences(["t1c", "t2"]) == ("t2", "t1c")  # no FLAIR: T2 is the primary
    assert multiseq_feature_names(["t1c", "t2"])[0] == "t2.intensity"


@pytest.mark.parametrize(
    "seqs, match",
    [(["flair", "FLAIR"], "twice"), (["flair", "dwi"], "unknown"), ([], "no sequence")],
)
def test_bad_sequence_lists_are_refused(seqs, match):
    with pytest.raises(InputError, match=match):
        order_sequences(seqs)


def test_sequences_on_different_grids_are_refused():
    fl, t2, _, sp = _pair(3)
    with pytest.raises(InputError, match="co-registered"):
        stack_features({"flair": fl, "t2": t2[:, :-1]}, spacing_mm=sp)
    with pytest.raises(InputError, match="without an image"):
        stack_features({"flair": fl}, spacing_mm=sp, priors={"t2": np.zeros(fl.shape, bool)})
    with pytest.raises(InputError, match="candidates shape"):
        compute_features(fl, spacing_mm=sp, modality="flair", candidates=np.ones((1, 2, 2), bool))


def test_a_tiny_model_reads_the_second_sequence():
    """Tumour visible on T2 only: FLAIR alone finds nothing, FLAIR + T2 finds it."""
    pytest.importorskip("lightgbm")
    from tumor3d.learned.forest import predict_proba
    from tumor3d.learned.training import TrainingRows, sample_rows, train_forest

    def fit(seqs):
        rng = np.random.default_rng(0)
        parts = []
        for seed in (1, 2, 4):
            fl, t2, truth, sp = _pair(seed, flair_tumour=False)
            imgs = {"flair": fl, "t2": t2}
            f = stack_features({s: imgs[s] for s in seqs}, spacing_mm=sp)
            parts.append(sample_rows(f, truth, rng=rng, n_lesion=1500, n_far=1500, n_band=1000))
        return train_forest(
            TrainingRows.concatenate(parts), num_rounds=40, params={"min_data_in_leaf": 20}
        )

    fl, t2, truth, sp = _pair(7, flair_tumour=False)
    imgs = {"flair": fl, "t2": t2}
    scores = {}
    for seqs in (("flair",), ("flair", "t2")):
        f = stack_features({s: imgs[s] for s in seqs}, spacing_mm=sp)
        prob = np.zeros(f.shape, np.float32)
        prob.ravel()[f.index] = predict_proba(fit(seqs), f.values)
        scores[seqs] = dice(prob >= 0.5, truth)
    assert scores[("flair",)] < 0.2
    assert scores[("flair", "t2")] > 0.7
