"""The learned method's review of the forest + U-Net mean: the models' disagreement.

The mean of two probabilities is smooth where the models disagree (1 and 0.4
average to a confident-looking 0.7), so the review measures the share of the
lesion where the forest and the network differ by more than 0.5
(``model_disagreement``, published) and judges the spread of the U-Net
ensemble's own nets inside the lesion (``net_spread``, chosen over the first
by cross-validation). A forest alone (no network to judge) has limits of its
own: voxels near the threshold per lesion voxel. No real data: constructed
maps, the shipped forest on a phantom, constant networks.
"""

from __future__ import annotations

import io
import json

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.learned.review import (
    REVIEW_LIMITS,
    review_features,
    review_kind,
    review_segmentation,
)


def _two_models(share: float):
    """A 2 x 20 x 20 lesion both models call tumour, the net doubting ``share`` of it."""
    forest = np.zeros((2, 30, 30), np.float32)
    forest[:, 5:25, 5:25] = 1.0
    net = forest.copy()
    n_rows = round(share * 20)  # the net's probability 0.45 on the first rows of the lesion
    net[:, 5 : 5 + n_rows, 5:25] = 0.45
    return forest, net, 0.5 * (forest + net)


def test_disagreeing_models_are_flagged_where_their_confident_mean_is_not():
    """With one net (a user's own: no ensemble spread) the review judges the forest's
    and the net's disagreement by the single net's limits; the shipped ensemble's
    review (with_net) judges its nets' spread instead."""
    forest, net, mean = _two_models(0.3)
    lesion = mean > 0.5
    assert lesion.sum() == 800  # the whole lesion is kept: the mean is 0.725 where they differ
    both = review_features(
        mean, lesion, (5.0, 1.0, 1.0), forest_probability=forest, cnn_probability=net
    )
    assert both["model_disagreement"] == pytest.approx(0.3)  # 6 of 20 rows, |1 - 0.45| > 0.5
    # the other figures see a confident lesion: mean 0.9175, nothing outside
    assert both["mean_probability"] == pytest.approx(0.7 + 0.3 * 0.725)
    assert both["mean_probability"] > REVIEW_LIMITS["with_net"]["mean_probability"]
    assert both["outside_ratio"] == 0.0
    assert "model_disagreement" not in REVIEW_LIMITS["with_net"]
    assert review_kind(both) == "single_net"
    flagged = review_segmentation(both)
    assert flagged.needs_review and len(flagged.reasons) == 1
    assert flagged.reasons[0].startswith("the forest and the U-Net disagree, check the outline")
    assert "on 30% of the lesion" in flagged.reasons[0]
    # the same mean without the two it came from (a forest alone): nothing to judge
    alone = review_features(mean, lesion, (5.0, 1.0, 1.0))
    assert np.isnan(alone["model_disagreement"])
    passed = review_segmentation(alone)
    assert not passed.needs_review and passed.quality_score > flagged.quality_score
    # models that agree (a disagreement under the limit) pass
    f2, n2, m2 = _two_models(0.05)
    agree = review_features(
        m2, m2 > 0.5, (5.0, 1.0, 1.0), forest_probability=f2, cnn_probability=n2
    )
    assert agree["model_disagreement"] == pytest.approx(0.05)
    assert agree["model_disagreement"] < REVIEW_LIMITS["single_net"]["model_disagreement"]
    assert not review_segmentation(agree).needs_review


def test_an_ensemble_whose_nets_disagree_is_flagged_where_their_mean_is_confident():
    """net_spread: the mean over the lesion of the largest minus the smallest of the
    nets' probabilities, against a naive loop; judged by the shipped limit."""
    forest, _, _ = _two_models(0.0)
    lesion = forest > 0.5
    limit = REVIEW_LIMITS["with_net"]["net_spread"]
    for share, doubt in ((0.4, 0.6), (0.1, 0.6)):  # rows of the lesion where one net says 0.4
        a = forest.copy()
        b = forest.copy()
        b[:, 5 : 5 + round(share * 20), 5:25] = 1.0 - doubt
        c = 0.5 * (a + b) + 0.0  # a third net in between: the range is still a to b
        members = np.stack([a, b, c])
        mean = members.mean(axis=0)
        prob = 0.5 * (forest + mean)
        fig = review_features(
            prob, lesion, (5.0, 1.0, 1.0), forest_probability=forest, cnn_probability=mean,
            cnn_members=members,
        )  # fmt: skip
        want = np.mean([max(m[i] for m in members) - min(m[i] for m in members)
                        for i in zip(*np.nonzero(lesion), strict=True)])  # fmt: skip
        assert fig["net_spread"] == pytest.approx(want) == pytest.approx(share * doubt)
        assert fig["mean_probability"] > REVIEW_LIMITS["with_net"]["mean_probability"]
        review = review_segmentation(fig)
        assert review.needs_review == (share * doubt > limit)
        if review.needs_review:
            assert review.reasons == (
                "the U-Net ensemble's nets disagree on the outline, check its edges: their "
                "probabilities differ by 0.24 on average inside the lesion (limit 0.10)",
            )
    # one net (or none): no spread; an empty lesion: 0; a mismatched shape: refused
    one = review_features(prob, lesion, (1.0, 1.0, 1.0), cnn_members=members[:1])
    assert np.isnan(one["net_spread"]) and np.isnan(
        review_features(prob, lesion, (1, 1, 1))["net_spread"]
    )
    empty = review_features(prob, np.zeros_like(lesion), (1.0, 1.0, 1.0), cnn_members=members)
    assert empty["net_spread"] == 0.0
    with pytest.raises(InputError, match="cnn_members"):
        review_features(prob, lesion, (1.0, 1.0, 1.0), cnn_members=members[:, :1])


def _uncertain_rim(rim: int):
    """A 10 x 10 lesion of probability 0.95 in a rim ``rim`` voxels wide of 0.4 (one slice)."""
    p = np.zeros((1, 40, 40), np.float32)
    p[0, 15 - rim : 25 + rim, 15 - rim : 25 + rim] = 0.4
    p[0, 15:25, 15:25] = 0.95
    return p


def test_a_forest_alone_is_judged_by_its_own_limits_and_a_net_case_is_not():
    """Without a net the review judges the uncertain boundary (voxels of probability
    0.2-0.8 per lesion voxel); with one, the same map's boundary is not judged."""
    wide, narrow = _uncertain_rim(3), _uncertain_rim(1)
    limit = REVIEW_LIMITS["forest_alone"]["uncertain_ratio"]
    assert "uncertain_ratio" not in REVIEW_LIMITS["with_net"]
    # 16 x 16 - 10 x 10 = 156 rim voxels per 100 lesion voxels; 12 x 12: 44
    alone = review_features(wide, wide > 0.5, (5.0, 1.0, 1.0))
    assert alone["uncertain_ratio"] == pytest.approx(1.56) and alone["uncertain_ratio"] > limit
    # confident inside, nothing above 0.5 left outside: the other figures pass
    assert alone["mean_probability"] == pytest.approx(0.95) and alone["outside_ratio"] == 0.0
    assert review_kind(alone) == "forest_alone"
    flagged = review_segmentation(alone)
    assert flagged.needs_review and len(flagged.reasons) == 1
    assert flagged.reasons[0].startswith("uncertain tumour edge, check the outline")
    assert "1.56 voxels" in flagged.reasons[0]
    # a narrow rim under the limit passes
    ok = review_features(narrow, narrow > 0.5, (5.0, 1.0, 1.0))
    assert ok["uncertain_ratio"] == pytest.approx(0.44)
    assert not review_segmentation(ok).needs_review
    # the same wide map as the mean of a forest and a net that agree: judged by the
    # net's limits (their disagreement, 0), not by the forest alone's boundary
    both = review_features(
        wide, wide > 0.5, (5.0, 1.0, 1.0), forest_probability=wide, cnn_probability=wide
    )
    assert both["uncertain_ratio"] == alone["uncertain_ratio"] and both["model_disagreement"] == 0
    assert review_kind(both) == "single_net"
    passed = review_segmentation(both)
    assert not passed.needs_review and passed.quality_score > flagged.quality_score


def test_the_disagreement_needs_both_probabilities_of_the_lesion_shape():
    forest, net, mean = _two_models(0.3)
    with pytest.raises(InputError, match="together"):
        review_features(mean, mean > 0.5, (1.0, 1.0, 1.0), forest_probability=forest)
    with pytest.raises(InputError, match="shapes"):
        review_features(
            mean, mean > 0.5, (1.0, 1.0, 1.0), forest_probability=forest[:1], cnn_probability=net
        )
    empty = review_features(
        mean, np.zeros(mean.shape, bool), (1.0, 1.0, 1.0), forest_probability=forest,
        cnn_probability=net,
    )  # fmt: skip
    assert empty["model_disagreement"] == 0.0
    with pytest.raises(InputError, match="no review check"):
        review_segmentation(empty, {"volume_ml": 1.0})


def _constant_net(p_logit: float):
    """A 2-level U-Net whose probability is ``sigmoid(p_logit)`` everywhere."""
    from tumor3d.learned.cnn import unet_from_bytes

    rng = np.random.default_rng(0)
    a, c = {}, 3
    for i, o in enumerate((2, 4)):
        for j, ci in enumerate((c, o)):
            a[f"enc{i}_{j}_w"] = rng.normal(0, 0.3, (o, ci, 3, 3))
            a[f"enc{i}_{j}_b"] = np.zeros(o)
        c = o
    for j, ci in enumerate((c + 2, 2)):
        a[f"dec0_{j}_w"] = rng.normal(0, 0.3, (2, ci, 3, 3))
        a[f"dec0_{j}_b"] = np.zeros(2)
    a["head_w"] = np.zeros((1, 2, 1, 1))
    a["head_b"] = np.array([p_logit])
    buf = io.BytesIO()
    meta = json.dumps({"settings": {"size": 32, "context": 1}}).encode()
    arrays = {k: v.astype(np.float32) for k, v in a.items()}
    np.savez(buf, **arrays, meta_json=np.frombuffer(meta, np.uint8))
    return unet_from_bytes(buf.getvalue())


def test_the_learned_method_measures_its_models_disagreeing_and_judges_its_ensemble():
    """segment_tumor (the pipeline's call) with a net sure of tumour everywhere: the
    mean keeps tissue the forest calls healthy; model_disagreement is the share of
    the lesion where the forest's own probability (learned_cnn off) is under 0.5.
    Given an ensemble of that net and an unsure one, their spread is judged."""
    from tumor3d.learned.cnn import unet_volume_probability
    from tumor3d.learned.shipped import shipped_model
    from tumor3d.phantom.patient import make_phantom_patient
    from tumor3d.segmentation.detect import SliceDetection
    from tumor3d.segmentation.segment import segment_tumor

    net = _constant_net(10.0)
    scan = make_phantom_patient(4, modality="flair", n_slices=10, matrix_size=(96, 96)).scan
    p_net = unet_volume_probability(net, scan.image)
    assert float(p_net.min()) > 0.999
    shape = scan.shape
    det = SliceDetection.from_records(
        [
            {"slice_index": z, "n_modes": 3, "abnormal": False, "peaks_gray": [], "brain_pixels": 0}
            for z in range(shape[0])
        ]
    )
    args = (np.zeros(shape, np.uint8), np.ones(shape, bool), det)
    kw = dict(modality="flair", method="learned", image=scan.image, cnn=net, spacing_mm=(5, 1, 1))
    kw["model"] = shipped_model("flair")
    off = segment_tumor(*args, learned_cnn="off", **kw)
    auto = segment_tumor(*args, learned_cnn="auto", **kw)
    assert np.isnan(off.review.figures["model_disagreement"])
    assert not any("U-Net" in r for r in off.review.reasons)
    lesion = auto.tumor_mask
    forest = off.probability
    want = float(np.mean(np.abs(forest[lesion] - p_net[lesion]) > 0.5))
    assert want > 0.5  # the tissue the forest doubts, kept by the net's certainty
    assert auto.review.figures["model_disagreement"] == pytest.approx(want)
    assert np.isnan(auto.review.figures["net_spread"])  # one net: no spread, its own limits
    assert review_kind(auto.review.figures) == "single_net" and auto.review.needs_review
    assert any(r.startswith("the forest and the U-Net disagree") for r in auto.review.reasons)
    # an ensemble of that net and a slightly less sure one: their spread in the lesion is
    # the difference of the two constants (judged: over a lowered limit, a reason)
    pair = segment_tumor(*args, learned_cnn="auto", **{**kw, "cnn": (net, _constant_net(8.0))})
    assert pair.tumor_mask.any()
    want_spread = 1.0 / (1.0 + np.exp(-10.0)) - 1.0 / (1.0 + np.exp(-8.0))
    assert pair.review.figures["net_spread"] == pytest.approx(want_spread, rel=1e-3)
    assert not any(r.startswith("the U-Net ensemble") for r in pair.review.reasons)
    lowered = review_segmentation(pair.review.figures, {"net_spread": want_spread / 2})
    assert any(r.startswith("the U-Net ensemble's nets disagree") for r in lowered.reasons)


def test_no_lesion_kept_is_said_in_words_not_as_an_infinite_ratio():
    """A map with uncertain and lesion-like voxels but no lesion kept: both ratios are
    infinite (nothing to divide by) and asked about, in words that name the empty lesion;
    "inf" never reaches a reason (it did: "inf voxels of probability 0.2-0.8 per lesion
    voxel" in a published review_reasons)."""
    p = np.zeros((3, 20, 20), np.float32)
    p[1, 4:8, 4:8] = 0.5  # uncertain
    p[1, 12:16, 12:16] = 0.9  # lesion-like, left outside the (empty) lesion
    figures = review_features(p, np.zeros(p.shape, bool), (5.0, 1.0, 1.0))
    assert figures["uncertain_ratio"] == figures["outside_ratio"] == float("inf")
    review = review_segmentation(figures, {"uncertain_ratio": 1.2})
    assert review.needs_review and len(review.reasons) == 2
    assert all("no lesion kept" in r and "inf" not in r for r in review.reasons)


def test_every_reason_says_what_to_check_before_its_figures():
    """A clinician reads the first words: each reason starts with what is doubted and what
    to look at, in words; the model's figure and limit come after (a user audit found the
    reasons model jargon: "outside_ratio 0.31")."""
    from tumor3d.learned.review import EMPTY_LESION_REASONS, REVIEW_CHECKS

    texts = [text for _, text in REVIEW_CHECKS.values()] + list(EMPTY_LESION_REASONS.values())
    for text in texts:
        words, _, _ = text.partition("{")
        assert "check" in words, text
        assert not any(c.isdigit() for c in words.replace("0.2-0.8", "")), text
