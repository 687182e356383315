"""The learned segmentation method: features, the flat forest, a tiny model on phantoms.

Real data never enters these tests: a tiny model is trained on phantoms
(LightGBM, the ``test`` extra) and judged on a phantom it did not see.
"""

from __future__ import annotations

import functools
import io
import json

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.evaluation.metrics import dice
from tumor3d.learned.features import FEATURE_NAMES, compute_features, tissue_foreground
from tumor3d.learned.forest import ForestModel, forest_from_lightgbm_dump, predict_proba
from tumor3d.learned.review import review_features, review_segmentation
from tumor3d.learned.segment import keep_main_lesion, segment_learned
from tumor3d.phantom.patient import make_phantom_patient
from tumor3d.segmentation.lesion import left_right_axis

lgb = pytest.importorskip("lightgbm")


@functools.cache
def _phantom(seed: int, modality: str = "flair"):
    """A 128 x 128 phantom's scan and truth, made once per file (read-only arrays)."""
    p = make_phantom_patient(seed, modality=modality, matrix_size=(128, 128))
    truth = np.asarray(p.slice_masks) > 0.5
    truth.setflags(write=False)
    return p.scan, truth


def _features(scan, prior=None):
    return compute_features(
        scan.image,
        spacing_mm=scan.spacing_zyx_mm,
        modality=scan.modality,
        lr_axis=left_right_axis(scan.affine),
        prior=prior,
    )


@pytest.fixture(scope="module")
def tiny_model() -> ForestModel:
    """A forest trained on three phantoms (not seed 7, the held-out one)."""
    from tumor3d.learned.training import TrainingRows, sample_rows, train_forest

    rng = np.random.default_rng(0)
    parts = []
    for seed in (1, 2, 3):
        scan, truth = _phantom(seed)
        parts.append(
            sample_rows(_features(scan), truth, rng=rng, n_lesion=1500, n_far=1500, n_band=1000)
        )
    return train_forest(
        TrainingRows.concatenate(parts),
        num_rounds=40,
        params={"min_data_in_leaf": 20},
        meta={"threshold": 0.5, "keep_fraction": 0.3},
    )


# --------------------------------------------------------------------------- features


def test_features_do_not_depend_on_the_intensity_scale():
    """An 8-bit export and a uint16 one of the same head give the same features."""
    scan, _ = _phantom(4)
    a = compute_features(scan.image, spacing_mm=scan.spacing_zyx_mm, modality="flair")
    b = compute_features(
        scan.image * 37.0 + 500.0, spacing_mm=scan.spacing_zyx_mm, modality="flair"
    )
    assert np.array_equal(a.index, b.index)
    assert a.values.shape == (a.index.size, len(FEATURE_NAMES))
    np.testing.assert_allclose(a.values, b.values, rtol=1e-3, atol=1e-3)


def test_tissue_is_the_head_with_its_holes_filled():
    img = np.zeros((3, 40, 40), np.float32)
    img[:, 5:35, 5:35] = 100.0  # the head
    img[:, 15:25, 15:25] = 2.0  # a dark ventricle inside: still tissue
    img[:, 0, 0] = 100.0  # a speck: not tissue (opened away)
    fg = tissue_foreground(img)
    assert fg.sum() == 3 * 30 * 30 and not fg[:, 0, 0].any()


def test_the_tissue_is_the_same_whatever_constant_border_surrounds_the_head():
    """Rows, columns and slices of the volume's lowest value around a head (an exporter's
    padding, a wider field of view, empty slices) do not move the tissue mask, which
    places the U-Net's window and normalises both models' intensities; neither does
    cropping them off. (A threshold of the whole array's histogram moved with the
    amount of air: 0.2-7 % of the tissue's voxels on the cross-validation's cases.)"""
    p = make_phantom_patient(3, modality="flair", n_slices=10)
    img = np.asarray(p.scan.image, np.float32)
    fg = tissue_foreground(img)
    assert 0.2 < fg.mean() < 0.9
    low = float(img.min())
    padded = np.pad(img, ((4, 7), (30, 9), (12, 41)), constant_values=low)
    np.testing.assert_array_equal(tissue_foreground(padded)[4:-7, 30:-9, 12:-41], fg)
    framed = img.copy()
    framed[:, :3], framed[:, :, -5:] = low, low  # the original's own border set to its floor
    cropped = framed[:, 3:, :-5]
    np.testing.assert_array_equal(tissue_foreground(cropped), tissue_foreground(framed)[:, 3:, :-5])


def test_prior_features_are_its_inside_and_signed_distance_mm():
    img = np.zeros((2, 60, 60), np.float32)
    img[:, 5:55, 5:55] = 100.0
    prior = np.zeros(img.shape, bool)
    prior[0, 20:30, 20:30] = True
    f = compute_features(img, spacing_mm=(5.0, 0.5, 0.5), modality="t2", prior=prior)
    col = {n: f.values[:, i] for i, n in enumerate(FEATURE_NAMES)}
    flat = {int(k): j for j, k in enumerate(f.index)}
    centre = flat[np.ravel_multi_index((0, 25, 25), img.shape)]
    outside = flat[np.ravel_multi_index((0, 25, 40), img.shape)]  # 11 px = 5.5 mm outside
    other_slice = flat[np.ravel_multi_index((1, 25, 25), img.shape)]
    assert col["prior_inside"][centre] == 1 and col["prior_inside"][outside] == 0
    assert col["prior_distance_mm"][centre] < 0
    assert col["prior_distance_mm"][outside] == pytest.approx(5.5)
    assert col["prior_slice_area"][other_slice] == 0 and col["prior_slice_area"][centre] == 1
    with pytest.raises(InputError, match="prior mask shape"):
        compute_features(img, spacing_mm=(5.0, 0.5, 0.5), modality="t2", prior=prior[:1])


@pytest.mark.parametrize("lr_axis", [2, 1, None])
def test_features_are_computed_on_the_tissue_box_alone(monkeypatch, lr_axis):
    """The features are computed on the box of the tissue (and the prior), not the whole
    volume; every row equals, bit for bit, the same features computed on the whole volume
    (the reference: the box widened to the volume). The volumes are built so that each
    margin of the box matters: a lopsided head whose mirror reaches past its own box, a
    prior outside the tissue, tissue in the first slice and a gap of empty slices, a
    phantom's head."""
    from tumor3d.learned import features

    rng = np.random.default_rng(3)
    img = np.zeros((9, 70, 90), np.float32)
    img[1:7, 12:50, 20:60] = 100.0  # the head, its mass to the left of its box's centre
    img[1:7, 20:40, 60:75] = 100.0  # a thin arm to the right: the mirror reaches past it
    img[0, 30:35, 30:40] = 100.0  # tissue in the first slice (the neighbour slice repeats)
    img[2, 25:33, 30:38] = 180.0  # a bright lesion
    img += rng.normal(0, 3, img.shape).astype(np.float32) * (img > 0)
    prior = np.zeros(img.shape, bool)
    prior[3, 52:60, 10:25] = True  # a prior partly outside the tissue's box
    prior[2, 25:33, 30:38] = True
    scan, _ = _phantom(4)
    cases = [
        (img, (5.0, 0.8, 0.6), prior),
        (img, (5.0, 0.8, 0.6), None),
        (np.asarray(scan.image, np.float32), scan.spacing_zyx_mm, None),
    ]
    for image, spacing_mm, pr in cases:
        boxed = compute_features(
            image, spacing_mm=spacing_mm, modality="t2", lr_axis=lr_axis, prior=pr
        )
        with monkeypatch.context() as m:  # the reference: the whole volume
            whole_box = lambda cand, *a: tuple(slice(0, n) for n in cand.shape)  # noqa: E731
            m.setattr(features, "_work_box", whole_box)
            whole = compute_features(
                image, spacing_mm=spacing_mm, modality="t2", lr_axis=lr_axis, prior=pr
            )
        np.testing.assert_array_equal(boxed.index, whole.index)
        np.testing.assert_array_equal(boxed.candidates, whole.candidates)
        assert boxed.shape == whole.shape == image.shape
        for j, name in enumerate(FEATURE_NAMES):
            np.testing.assert_array_equal(boxed.values[:, j], whole.values[:, j], err_msg=name)
    # the box is smaller than the volume here (else the test compares a thing with itself)
    box = features._work_box(tissue_foreground(img), prior, lr_axis, 40.0)
    assert np.prod([s.stop - s.start for s in box]) < 0.8 * img.size


# --------------------------------------------------------------------------- the forest


def test_flat_forest_predicts_as_lightgbm():
    """The numba walk of the flattened trees equals LightGBM's own prediction."""
    rng = np.random.default_rng(1)
    x = rng.normal(size=(3000, 5)).astype(np.float32)
    y = ((x[:, 0] + 0.5 * x[:, 1] ** 2 - x[:, 3]) > 0.3).astype(int)
    booster = lgb.train(
        {"objective": "binary", "verbose": -1, "num_leaves": 15},
        lgb.Dataset(x, label=y),
        num_boost_round=25,
    )
    model = forest_from_lightgbm_dump(booster.dump_model())
    test = rng.normal(size=(500, 5)).astype(np.float32)
    np.testing.assert_allclose(predict_proba(model, test), booster.predict(test), atol=1e-6)


def test_the_walk_sums_every_tree_as_a_naive_walk_does_bit_for_bit(tiny_model):
    """The blocked, four-rows-at-once walk in float32 against a naive walk of one row
    through one tree after another in float64, on rows that sit exactly on thresholds
    (a float32 ``x`` beside a float64 ``t`` it rounds to, above or below it) and
    row counts that leave a block's last rows outside the groups of four."""
    from tumor3d.learned.forest import predict_logit

    m = tiny_model

    def naive(x):
        out = np.zeros(len(x))
        for i, row in enumerate(x.astype(np.float64)):
            for root in m.roots:
                node = root
                while m.feature[node] >= 0:
                    go_left = row[m.feature[node]] <= m.threshold[node]
                    node = m.left[node] if go_left else m.right[node]
                out[i] += m.value[node]
        return out

    scan, _ = _phantom(7)
    x = _features(scan).values[::7][:2051].copy()
    rng = np.random.default_rng(5)
    split = np.flatnonzero(m.feature >= 0)
    for i in range(0, len(x), 3):  # a third of the rows: one feature put on a threshold
        k = rng.choice(split)
        x[i, m.feature[k]] = np.float32(m.threshold[k])  # rounds up or down
    ties = [np.float32(m.threshold[k]) != m.threshold[k] for k in split]
    assert any(ties)  # thresholds a float32 cannot hold: the float32 compare is tested
    for n in (2051, 1027, 5, 1):
        np.testing.assert_array_equal(predict_logit(m, x[:n]), naive(x[:n]))


def test_model_round_trip_is_plain_arrays_and_refuses_pickles(tiny_model):
    data = tiny_model.to_bytes()
    back = ForestModel.from_bytes(data)
    assert back.digest() == tiny_model.digest() and back.meta == tiny_model.meta
    # an .npz holding an object array (a pickle) is refused, never unpickled
    buf = io.BytesIO()
    arrays = {
        k: getattr(tiny_model, k)
        for k in ("feature", "threshold", "left", "right", "value", "roots")
    }
    np.savez(buf, meta=np.array([{"x": 1}], dtype=object), **arrays)
    with pytest.raises(InputError, match="not a readable tumor3d forest model"):
        ForestModel.from_bytes(buf.getvalue())
    assert json.loads(json.dumps(back.meta)) == back.meta


def _npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array)
    return buf.getvalue()


def _npz(**arrays: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


@pytest.mark.parametrize(
    ("damage", "why"),
    [
        (lambda data: data[: len(data) // 2], "BadZipFile"),  # cut short
        (lambda data: b"not an npz", "never unpickled"),  # a text file
        (lambda data: data[:-40] + bytes(40), None),  # its end overwritten
        (lambda data: _npy(np.zeros(3)), "a single array, not an .npz"),  # one .npy array
        (lambda data: _npz(x=np.zeros(3)), "no array feature)"),  # another archive
    ],
)
def test_a_damaged_model_file_is_one_line_naming_it_not_a_traceback(tiny_model, damage, why):
    """A model file cut short or replaced (a user audit: a truncated hyper.npz gave a
    151-line BadZipFile traceback; a text file was answered with allow_pickle advice)."""
    with pytest.raises(InputError) as exc:
        ForestModel.from_bytes(damage(tiny_model.to_bytes()), source="models/hyper.npz")
    text = str(exc.value)
    assert text.startswith("models/hyper.npz: not a readable tumor3d forest model (")
    assert "\n" not in text and "allow_pickle" not in text
    assert why is None or why in text


def test_a_model_of_another_family_is_refused_naming_both(tiny_model, monkeypatch):
    """A T1c (tumour core) model copied over hyper.npz (FLAIR, T2 whole tumour) was used
    silently (a user audit: 17.7 mL against 15.3 mL, status check; through the API, ok)."""
    from dataclasses import replace

    from tumor3d.learned.shipped import check_family

    t1c = replace(tiny_model, meta={**tiny_model.meta, "family": "t1c", "modalities": ["t1c"]})
    with pytest.raises(InputError) as exc:
        check_family(t1c, "hyper", "tumor3d/learned/models/hyper.npz")
    assert str(exc.value) == (
        "tumor3d/learned/models/hyper.npz: a model trained for t1c (t1c), not hyper (flair, "
        "t2): put the hyper model there (`tumor3d train` writes hyper.npz)"
    )
    check_family(t1c, "t1c", "t1c.npz")  # its own family
    check_family(tiny_model, "hyper", "hyper.npz")  # no record: taken as it is
    # as the shipped files are read: hyper.npz holding the T1c model is refused
    import tumor3d.learned.shipped as shipped

    monkeypatch.setattr(shipped.ForestModel, "from_bytes", lambda data, source: t1c)
    with pytest.raises(InputError, match="a model trained for t1c"):
        shipped._load.__wrapped__("hyper")


def test_a_forest_pointing_outside_its_nodes_is_refused():
    with pytest.raises(InputError, match="outside the node table"):
        ForestModel(
            np.array([0], np.int32),
            np.zeros(1),
            np.array([5], np.int32),
            np.array([6], np.int32),
            np.zeros(1),
            np.array([0], np.int32),
        )


# --------------------------------------------------------------------------- segmentation


def test_tiny_model_finds_an_unseen_phantom_tumour(tiny_model):
    scan, truth = _phantom(7)
    seg = segment_learned(
        scan.image,
        model=tiny_model,
        spacing_mm=scan.spacing_zyx_mm,
        modality="flair",
        lr_axis=left_right_axis(scan.affine),
    )
    assert seg.probability.shape == scan.shape
    assert 0.0 <= seg.probability.min() and seg.probability.max() <= 1.0
    assert dice(seg.mask, truth) > 0.75
    vol_err = abs(int(seg.mask.sum()) - int(truth.sum())) / truth.sum()
    assert vol_err < 0.3


def test_tiny_model_finds_nothing_much_in_a_tumour_free_phantom(tiny_model):
    p = make_phantom_patient(7, modality="flair", matrix_size=(128, 128), tumor=False)
    scan = p.scan
    seg = segment_learned(
        scan.image,
        model=tiny_model,
        spacing_mm=scan.spacing_zyx_mm,
        modality="flair",
        lr_axis=left_right_axis(scan.affine),
    )
    _, with_tumour = _phantom(7)
    assert seg.mask.sum() < 0.1 * with_tumour.sum()


def test_a_model_of_other_features_is_refused(tiny_model):
    import dataclasses

    other = dataclasses.replace(tiny_model, meta={**tiny_model.meta, "feature_names": ["a"]})
    scan, _ = _phantom(7)
    with pytest.raises(InputError, match="retrain"):
        segment_learned(scan.image, model=other, spacing_mm=scan.spacing_zyx_mm, modality="flair")


def test_keep_main_lesion_keeps_the_heaviest_region_and_its_peers():
    p = np.zeros((3, 30, 30), np.float32)
    p[1, 2:12, 2:12] = 0.9  # 100 voxels, mass 90
    p[1, 20:26, 20:26] = 0.8  # 36 voxels, mass 28.8 (>= 0.3 x 90: a peer, kept)
    p[1, 2:4, 25:27] = 0.95  # 4 voxels, mass 3.8: dropped
    m = keep_main_lesion(p, 0.5, keep_fraction=0.3, min_voxels=1)
    assert m.sum() == 136
    assert keep_main_lesion(p, 0.5, keep_fraction=0.5, min_voxels=1).sum() == 100
    assert not keep_main_lesion(p, 0.96, min_voxels=1).any()


def test_keep_main_lesion_chooses_among_the_regions_the_preferred_mask_touches():
    p = np.zeros((3, 30, 30), np.float32)
    p[1, 2:12, 2:12] = 0.9  # 100 voxels, mass 90: the heaviest
    p[1, 20:26, 20:26] = 0.8  # 36 voxels, mass 28.8
    p[1, 2:4, 25:27] = 0.95  # 4 voxels
    prefer = np.zeros(p.shape, bool)
    prefer[1, 22, 22] = True  # touches the lighter region only
    m = keep_main_lesion(p, 0.5, keep_fraction=1.0, min_voxels=1, prefer=prefer)
    assert m.sum() == 36 and m[1, 22, 22]
    # touching only a region too small to keep, or nothing: the choice is as without it
    prefer[:] = False
    prefer[1, 2, 25] = True
    assert keep_main_lesion(p, 0.5, keep_fraction=1.0, min_voxels=10, prefer=prefer).sum() == 100
    assert keep_main_lesion(p, 0.5, keep_fraction=1.0, prefer=np.zeros(p.shape, bool)).sum() == 100
    # with prefer_only, no lesion then: none of the regions large enough touches it
    only = {"keep_fraction": 1.0, "prefer_only": True}
    assert keep_main_lesion(p, 0.5, min_voxels=10, prefer=prefer, **only).sum() == 0
    assert keep_main_lesion(p, 0.5, prefer=np.zeros(p.shape, bool), **only).sum() == 0
    prefer[1, 22, 22] = True  # and as without it where one does
    assert keep_main_lesion(p, 0.5, min_voxels=10, prefer=prefer, **only).sum() == 36
    with pytest.raises(InputError, match="prefer has shape"):
        keep_main_lesion(p, 0.5, prefer=np.zeros((3, 30, 31), bool))


def test_on_t1c_the_lesion_is_chosen_where_the_prior_is(tiny_model, monkeypatch):
    # segment_learned hands the prior (the robust method's mask) to the region's choice on
    # T1c only (PRIOR_CHOOSES_REGION), and there only: a T1c lesion the prior does not touch
    # is none; the FLAIR and T2 lesions are chosen as before
    import tumor3d.learned.segment as learned_segment

    seen = []
    real = learned_segment.keep_main_lesion

    def spy(*args, **kwargs):
        seen.append((kwargs.get("prefer"), kwargs.get("prefer_only", False)))
        return real(*args, **kwargs)

    monkeypatch.setattr(learned_segment, "keep_main_lesion", spy)
    scan, truth = _phantom(7)
    prior = truth.copy()
    found = {}
    for modality, given in (("flair", prior), ("t2", prior), ("t1c", prior), ("t1c", None)):
        found[modality, given is None] = learned_segment.segment_learned(
            scan.image, model=tiny_model, spacing_mm=scan.spacing_zyx_mm, modality=modality,
            lr_axis=left_right_axis(scan.affine), prior=given,
        ).mask  # fmt: skip
    assert seen[0] == (None, False) and seen[1] == (None, False)
    assert seen[2][0] is prior and seen[2][1] is True
    assert seen[3] == (None, False)  # no prior given: every region, as on FLAIR
    assert found["t1c", False].any() and found["t1c", True].any()
    # the prior elsewhere (a region of its own the model does not find): no T1c lesion
    away = np.zeros_like(prior)
    away[:, :3, :3] = True
    none = learned_segment.segment_learned(
        scan.image, model=tiny_model, spacing_mm=scan.spacing_zyx_mm, modality="t1c",
        lr_axis=left_right_axis(scan.affine), prior=away,
    ).mask  # fmt: skip
    assert not none.any()


def test_review_flags_a_doubtful_map_and_passes_a_confident_one():
    sure = np.zeros((2, 20, 20), np.float32)
    sure[:, 5:15, 5:15] = 0.97
    good = review_segmentation(review_features(sure, sure > 0.5, (5.0, 1.0, 1.0)))
    assert not good.needs_review and good.quality_score > 0.9
    unsure = sure.copy()
    unsure[:, 3:17, 3:17] = np.maximum(unsure[:, 3:17, 3:17], 0.5)  # a wide uncertain rim
    unsure[:, 5:15, 5:15] = 0.6
    bad = review_segmentation(review_features(unsure, unsure > 0.55, (5.0, 1.0, 1.0)))
    assert bad.needs_review and bad.quality_score < good.quality_score
    assert any("confidence" in r for r in bad.reasons)


def test_segment_tumor_learned_needs_the_image_and_a_model():
    from tumor3d.segmentation.detect import SliceDetection
    from tumor3d.segmentation.segment import segment_tumor

    shape = (4, 32, 32)
    det = SliceDetection.from_records(
        [
            {"slice_index": z, "n_modes": 3, "abnormal": False, "peaks_gray": [], "brain_pixels": 0}
            for z in range(shape[0])
        ]
    )
    with pytest.raises(InputError, match="learned method needs"):
        segment_tumor(
            np.zeros(shape, np.uint8), np.ones(shape, bool), det, modality="flair", method="learned"
        )


# --------------------------------------------------------------------------- the shipped model


def test_shipped_models_load_without_pickle_and_name_their_features():
    from tumor3d.learned.shipped import model_family, shipped_model

    for modality, family in (("flair", "hyper"), ("T2", "hyper"), ("t1c", "t1c")):
        assert model_family(modality) == family
        m = shipped_model(modality)
        assert tuple(m.meta["feature_names"]) == FEATURE_NAMES
        assert 0.0 < m.meta["threshold"] < 1.0 and m.meta["training_cases"]
    with pytest.raises(InputError, match="no learned model"):
        model_family("dwi")


def test_default_on_an_unseen_flair_phantom_is_the_shipped_model_and_accurate():
    """``auto`` on FLAIR runs the shipped model (trained on real cases and phantom seeds
    1000-1009) and recovers a phantom it never saw: Eq. 7 against the exact truth."""
    import tumor3d

    p = make_phantom_patient(5, modality="flair")
    truth = np.asarray(p.slice_masks) > 0.5
    r = tumor3d.reconstruct_scan(p.scan)
    assert r.method == "learned"
    assert r.tumor_probability is not None and r.tumor_probability.shape == p.scan.shape
    assert dice(r.tumor_mask_slices, truth) > 0.9
    dy, dx = p.scan.pixel_spacing_mm
    truth_eq7_mm3 = float(np.asarray(p.slice_masks).sum()) * dy * dx * p.scan.slice_step_mm
    assert abs(r.volumes_mm3["eq7"] - truth_eq7_mm3) / truth_eq7_mm3 < 0.10


# --------------------------------------------------------------------------- auto-context


def test_context_features_read_the_first_stage_map_around_each_pixel():
    """Independent expectations on a square lesion map: rings, slices, distances."""
    from tumor3d.learned.context import CONTEXT_NAMES, context_features

    p = np.zeros((4, 80, 80), np.float32)
    p[1, 5:75, 5:75] = 0.8  # one slice holds the lesion
    p[1, 12, 12] = 1.0
    lesion = p > 0.5
    tissue = np.ones(p.shape, bool)
    pix = [(1, 40, 40), (1, 2, 40), (2, 40, 40), (3, 40, 40), (0, 78, 1)]
    idx = np.ravel_multi_index(tuple(np.array(pix).T), p.shape)
    c = context_features(p, lesion, candidates=tissue, index=idx, spacing_mm=(5.0, 0.5, 0.5))
    col = {n: c[:, i] for i, n in enumerate(CONTEXT_NAMES)}
    assert c.shape == (5, len(CONTEXT_NAMES))
    assert col["s1_prob"].tolist() == pytest.approx([0.8, 0.0, 0.0, 0.0, 0.0])
    # the ring (10 mm = 20 px) of the centre lies inside the square, of the edge pixel half out
    assert col["s1_ring_min"][0] == pytest.approx(0.8, abs=1e-3)
    assert col["s1_ring_min"][1] == 0.0 and col["s1_ring_max"][1] > 0.7
    # 0.5 mm pixels: the centre is 35 px = 17.5 mm inside, the edge pixel 3 px = 1.5 mm outside
    assert col["s1_distance_mm"][0] == pytest.approx(-17.5)
    assert col["s1_distance_mm"][1] == pytest.approx(1.5)
    # the next slice: one 5 mm step away in 3-D, the one after two
    assert col["s1_distance_3d_mm"][2] == pytest.approx(5.0)
    assert col["s1_distance_3d_mm"][3] == pytest.approx(10.0)
    assert col["s1_neighbour_max"][2] > 0.7 and col["s1_neighbour_max"][3] < 0.01
    assert col["s1_slice_max"].tolist() == pytest.approx([1.0, 1.0, 0.0, 0.0, 0.0])
    assert col["s1_slice_mean"][0] == pytest.approx(float(p[1].mean()))
    assert col["s1_slice_area"].tolist() == pytest.approx([1.0, 1.0, 0.0, 0.0, 0.0])
    with pytest.raises(InputError, match="one 3-D shape"):
        context_features(p, lesion[:2], candidates=tissue, index=idx, spacing_mm=(5, 1, 1))


def _small(seed: int, modality: str = "flair"):
    p = make_phantom_patient(seed, modality=modality, matrix_size=(96, 96))
    return p.scan, np.asarray(p.slice_masks) > 0.5


def test_auto_context_stage_two_sees_out_of_fold_maps_only(monkeypatch):
    """The first-stage models whose maps train the second stage never saw that patient:
    with two patients of two sequences each, every out-of-fold fit holds exactly the
    other patient's rows."""
    from tumor3d.learned import training

    cases, spacing, sizes = [], [], {}
    for seed in (1, 2):
        for mod in ("flair", "t2"):
            scan, truth = _small(seed, mod)
            cases.append((_features(scan), truth))
            spacing.append(scan.spacing_zyx_mm)
    small = {"n_lesion": 300, "n_far": 300, "n_band": 200}
    rng = np.random.default_rng(0)
    for i, (f, lab) in enumerate(cases):
        sizes[i] = training.sample_rows(f, lab, rng=rng, **small).y.size
    fits: list[int] = []
    real = training.train_forest

    def spy(rows, **kw):
        fits.append(rows.y.size)
        return real(rows, **kw)

    monkeypatch.setattr(training, "train_forest", spy)
    model = training.train_auto_context(
        cases,
        spacing_mm=spacing,
        patients=["a", "a", "b", "b"],
        folds=5,
        sample=small,
        num_rounds=10,
        params={"min_data_in_leaf": 20},
    )
    patient_rows = [sizes[0] + sizes[1], sizes[2] + sizes[3]]
    # fold 0 holds patient a: its map comes from a fit on b alone; then b's from a alone
    assert fits[:2] == [patient_rows[1], patient_rows[0]]
    assert fits[2:] == [sum(patient_rows)] * 2  # the final stages: every row
    assert model.context is not None and model.context.context is None
    with pytest.raises(InputError, match="two patients"):
        training.train_auto_context(cases[:2], spacing_mm=spacing[:2], patients=["a", "a"])


@pytest.fixture(scope="module")
def tiny_two_stage() -> ForestModel:
    from tumor3d.learned.training import train_auto_context

    cases, spacing = [], []
    for seed in (1, 2, 3):
        scan, truth = _phantom(seed)
        cases.append((_features(scan), truth))
        spacing.append(scan.spacing_zyx_mm)
    return train_auto_context(
        cases,
        spacing_mm=spacing,
        folds=3,
        threshold=0.5,
        keep_fraction=0.3,
        sample={"n_lesion": 1500, "n_far": 1500, "n_band": 1000},
        num_rounds=40,
        params={"min_data_in_leaf": 20},
    )


def test_two_stage_model_round_trips_and_finds_an_unseen_phantom_tumour(tiny_two_stage):
    from tumor3d.learned.context import CONTEXT_NAMES

    back = ForestModel.from_bytes(tiny_two_stage.to_bytes())
    assert back.context is not None and back.digest() == tiny_two_stage.digest()
    assert tuple(back.context.meta["feature_names"]) == FEATURE_NAMES + CONTEXT_NAMES
    one_stage = ForestModel.from_bytes(back.to_bytes())
    import dataclasses

    assert dataclasses.replace(one_stage, context=None).digest() != back.digest()
    scan, truth = _phantom(7)
    kw = dict(
        spacing_mm=scan.spacing_zyx_mm, modality="flair", lr_axis=left_right_axis(scan.affine)
    )
    seg = segment_learned(scan.image, model=back, **kw)
    assert dice(seg.mask, truth) > 0.75
    assert abs(int(seg.mask.sum()) - int(truth.sum())) / truth.sum() < 0.3
    # the answer is the second stage's: without it the probability differs
    first = segment_learned(scan.image, model=dataclasses.replace(back, context=None), **kw)
    assert not np.allclose(first.probability, seg.probability)
    # a second stage of other features is refused
    other = dataclasses.replace(
        back, context=dataclasses.replace(back.context, meta={"feature_names": ["a"]})
    )
    with pytest.raises(InputError, match="retrain"):
        segment_learned(scan.image, model=other, **kw)


# --------------------------------------------------------------------------- the U-Net beside


def _tiny_unet_bytes(seed: int = 0, size: int = 32) -> bytes:
    """A random 2-level U-Net (base 2, 3 input channels) as weight-file bytes, no torch."""
    rng = np.random.default_rng(seed)
    a, c = {}, 3
    for i, o in enumerate((2, 4)):
        for j, ci in enumerate((c, o)):
            a[f"enc{i}_{j}_w"] = rng.normal(0, np.sqrt(2 / (9 * ci)), (o, ci, 3, 3))
            a[f"enc{i}_{j}_b"] = rng.normal(0, 0.1, o)
        c = o
    for j, ci in enumerate((c + 2, 2)):
        a[f"dec0_{j}_w"] = rng.normal(0, np.sqrt(2 / (9 * ci)), (2, ci, 3, 3))
        a[f"dec0_{j}_b"] = rng.normal(0, 0.1, 2)
    a["head_w"] = rng.normal(0, 1.0, (1, 2, 1, 1))
    a["head_b"] = np.array([0.5])
    meta = {"settings": {"size": size, "context": 1}}
    buf = io.BytesIO()
    arrays = {k: v.astype(np.float32) for k, v in a.items()}
    np.savez(buf, **arrays, meta_json=np.frombuffer(json.dumps(meta).encode(), np.uint8))
    return buf.getvalue()


def test_with_a_unet_the_probability_is_the_mean_of_the_forest_and_the_network(tiny_model):
    from tumor3d.learned.cnn import unet_from_bytes, unet_volume_probability

    net = unet_from_bytes(_tiny_unet_bytes())
    scan, _ = _phantom(7)
    kw = dict(
        spacing_mm=scan.spacing_zyx_mm, modality="flair", lr_axis=left_right_axis(scan.affine)
    )
    alone = segment_learned(scan.image, model=tiny_model, **kw)
    both = segment_learned(scan.image, model=tiny_model, cnn=net, **kw)
    p_net = unet_volume_probability(net, scan.image)
    assert 0.05 < float(p_net.std())  # the random net is no constant
    np.testing.assert_allclose(both.probability, 0.5 * (alone.probability + p_net), atol=1e-6)
    np.testing.assert_array_equal(both.forest_probability, alone.probability)
    assert alone.forest_probability is None and alone.cnn_probability is None
    # the same cut and main region as the forest's alone, on the mean
    voxel_mm3 = float(np.prod(scan.spacing_zyx_mm))
    want = keep_main_lesion(
        both.probability, 0.5, keep_fraction=0.3, min_voxels=max(1, round(20.0 / voxel_mm3))
    )
    np.testing.assert_array_equal(both.mask, want)
    # an ensemble (the shipped pair of seeds): the mean of its nets' probabilities
    other = unet_from_bytes(_tiny_unet_bytes(3))
    pair = segment_learned(scan.image, model=tiny_model, cnn=(net, other), **kw)
    p_pair = 0.5 * (p_net + unet_volume_probability(other, scan.image))
    np.testing.assert_allclose(pair.cnn_probability, p_pair, atol=1e-6)
    np.testing.assert_allclose(pair.probability, 0.5 * (alone.probability + p_pair), atol=1e-6)
    for bad in ("net", (), (net, "net")):
        with pytest.raises(InputError, match="UNetWeights"):
            segment_learned(scan.image, model=tiny_model, cnn=bad, **kw)


def _shipped_from(monkeypatch, tmp_path, files: dict[str, bytes]):
    """shipped.py reading its models from ``tmp_path/models`` (``files``: name -> bytes)."""
    from tumor3d.learned import shipped

    (tmp_path / "models").mkdir()
    for name, data in files.items():
        (tmp_path / "models" / name).write_bytes(data)
    monkeypatch.setattr(shipped.resources, "files", lambda package: tmp_path)
    shipped._load_cnn.cache_clear()
    return shipped


@pytest.mark.parametrize("data", [None, b"not a zip", b"PK\x03\x04 truncated"])
def test_a_missing_or_corrupt_unet_file_is_one_line_naming_it(monkeypatch, tmp_path, data):
    """The second net of the ensemble missing or corrupt: one line naming that file."""
    files = {"unet_flair_seed0.npz": _tiny_unet_bytes()}
    if data is not None:
        files["unet_flair_seed1.npz"] = data
    shipped = _shipped_from(monkeypatch, tmp_path, files)
    try:
        with pytest.raises(InputError) as err:
            shipped.shipped_cnn("flair")
        text = str(err.value.problem)
        assert "\n" not in text and "tumor3d/learned/models/unet_flair_seed1.npz" in text
    finally:
        shipped._load_cnn.cache_clear()


def test_the_unet_ensemble_serves_flair_only_and_is_read_once(monkeypatch, tmp_path):
    files = {f"unet_flair_seed{s}.npz": _tiny_unet_bytes(s) for s in (0, 1)}
    shipped = _shipped_from(monkeypatch, tmp_path, files)
    try:
        nets = shipped.shipped_cnn("FLAIR")
        assert len(nets) == 2 and nets[0].sha256 != nets[1].sha256
        assert all(a is b for a, b in zip(nets, shipped.shipped_cnn("flair"), strict=True))
        assert nets[0].size == 32
        assert shipped.shipped_cnn("t2") is None and shipped.shipped_cnn("t1c") is None
    finally:
        shipped._load_cnn.cache_clear()


def test_the_shipped_unets_load_and_each_ones_bytes_move_the_segment_key(tmp_path):
    """The U-Net files are data of tumor3d.learned.shipped: the bytes of each enter the
    segment stage's code digest (``DATA_FILES``), so other weights recompute."""
    import hashlib
    import shutil

    from tumor3d.learned.shipped import CNN_MODELS, shipped_cnn
    from tumor3d.package_layout import SOURCE_FOLDERS
    from tumor3d.tasks.caching import PROJECT_ROOT, code_digest, module_closure

    nets = shipped_cnn("flair")
    names = CNN_MODELS["flair"]
    assert len(nets) == len(names) == 2
    for net, name in zip(nets, names, strict=True):
        shipped_file = PROJECT_ROOT / "tumor3d" / "learned" / "models" / f"{name}.npz"
        assert net.sha256 == hashlib.sha256(shipped_file.read_bytes()).hexdigest()
        assert net.in_channels == 2 * net.context + 1 and net.size % 2 ** (net.levels - 1) == 0
    assert nets[0].sha256 != nets[1].sha256 and nets[0].meta["seed"] != nets[1].meta["seed"]
    for folder in SOURCE_FOLDERS:  # tumor3d/ and the folders mapped into it (tasks/, ...)
        shutil.copytree(
            PROJECT_ROOT / folder, tmp_path / folder, ignore=shutil.ignore_patterns("__pycache__")
        )
    try:
        digests = [code_digest(("tumor3d.tasks.segment",), str(tmp_path))]
        for name in names:
            copy = tmp_path / "tumor3d" / "learned" / "models" / f"{name}.npz"
            copy.write_bytes(copy.read_bytes() + b"\0")
            code_digest.cache_clear()
            digests.append(code_digest(("tumor3d.tasks.segment",), str(tmp_path)))
        assert len(set(digests)) == 3
    finally:
        module_closure.cache_clear()
        code_digest.cache_clear()


@pytest.mark.parametrize("fov", [{}, {"matrix_size": (224, 224), "pixel_spacing_mm": 1.25}])
def test_the_shipped_unets_window_ignores_in_plane_air_and_crops(fov):
    """The shipped nets see 240 mm centred on the head (``framing: mm``), so a scan
    padded in-plane with air, or cropped near the head, gets the same probability on
    the voxels it shares with the scan as stored, whatever its field of view (the
    phantom's 240 mm, or 280 mm: a window of 192 of its 224 pixels). Nets that
    resample the whole slice (``slice``, shipped before) moved held-out masks by
    8-25 % of their voxels. (The head's tissue mask, which places the window, is the
    same here; on real heads it moves with the amount of noisy air: fov_end_to_end.py.)"""
    from tumor3d.learned.cnn import unet_volume_probability
    from tumor3d.learned.cnn_data import frame_of
    from tumor3d.learned.shipped import shipped_cnn

    nets = shipped_cnn("flair")
    assert {n.framing for n in nets} == {"mm"}
    p = make_phantom_patient(7, modality="flair", n_slices=12, **fov)
    img = np.asarray(p.scan.image, np.float32)
    pixel_mm = tuple(p.scan.pixel_spacing_mm)
    side = frame_of(img, "mm", pixel_mm)[2]
    assert side == round(240.0 / pixel_mm[0]) and (side < img.shape[1]) == bool(fov)
    want = unet_volume_probability(nets, img, pixel_mm=pixel_mm)
    assert want.max() > 0.5  # it sees the tumour
    pad = ((0, 0), (20, 9), (13, 20))
    padded = np.pad(img, pad, constant_values=float(img.min()))
    got = unet_volume_probability(nets, padded, pixel_mm=pixel_mm)
    np.testing.assert_allclose(got[:, 20:-9, 13:-20], want, atol=1e-5)
    rows, cols = np.nonzero((img > np.percentile(img, 60)).any(axis=0))
    r0, c0 = max(0, rows.min() - 4), max(0, cols.min() - 4)
    cropped = img[:, r0 : rows.max() + 5, c0 : cols.max() + 5]
    got = unet_volume_probability(nets, cropped, pixel_mm=pixel_mm)
    np.testing.assert_allclose(got, want[:, r0 : rows.max() + 5, c0 : cols.max() + 5], atol=1e-5)


def test_the_stage_writes_the_mean_on_flair_and_off_writes_the_forest_alone(monkeypatch, tmp_path):
    """The segment stage with a tiny random U-Net standing in for the shipped one: the
    probability it writes is the mean of the forest's (learned_cnn: off) and the
    network ensemble's; the nets' SHA-256s and the words "forest + U-Net mean" go with it."""
    from tumor3d.flows.patient import run_stages_direct
    from tumor3d.learned import shipped
    from tumor3d.learned.cnn import unet_from_bytes, unet_volume_probability
    from tumor3d.storage.nifti import probability_for_storage
    from tumor3d.storage.phantom_io import write_phantom_patient
    from tumor3d.storage.store import ArtifactStore

    nets = (unet_from_bytes(_tiny_unet_bytes(1)), unet_from_bytes(_tiny_unet_bytes(4)))
    monkeypatch.setattr(shipped, "shipped_cnn", lambda m: nets if m.lower() == "flair" else None)
    patient = make_phantom_patient(4, modality="flair", n_slices=10, matrix_size=(96, 96))
    image = write_phantom_patient(patient, tmp_path / "in").image
    written, values = {}, {}
    for mode in ("auto", "off"):
        store = tmp_path / f"store-{mode}"
        cfg = {"segment": {"learned_cnn": mode}}
        run = run_stages_direct(image, store, config=cfg, patient_id="u", modality="flair")
        out = run.outputs["segment-tumor"]
        written[mode], _ = ArtifactStore(store).get_volume(out.artifacts["tumor_probability"])
        values[mode] = out.values
        scan = ArtifactStore(store).get_scan(run.outputs["ingest-scan"].artifacts["scan"],
                                             patient_id="u")  # fmt: skip
    p_net = 0.5 * sum(unet_volume_probability(n, scan.image) for n in nets)
    # stored to 1/255 (tumor3d.storage.nifti.probability_for_storage): each side within 1/510
    for mode in written:
        np.testing.assert_array_equal(written[mode], probability_for_storage(written[mode]))
    np.testing.assert_allclose(written["auto"], 0.5 * (written["off"] + p_net), atol=1 / 255)
    # the forest alone is 0 outside the head's tissue; the random network is not
    outside = written["off"] == 0
    assert outside.any() and float(np.abs(written["auto"] - written["off"])[outside].max()) > 0.01
    assert values["auto"]["segment_model"] == "forest + U-Net mean"
    assert values["auto"]["cnn_sha256"] == [n.sha256 for n in nets]
    assert values["auto"]["cnn_model"] == ["unet_flair_seed0", "unet_flair_seed1"]
    assert values["off"]["segment_model"] == "forest" and "cnn_sha256" not in values["off"]
    assert values["auto"]["model_sha256"] == values["off"]["model_sha256"]


def test_the_api_averages_on_flair_unless_off_and_the_core_obeys_the_switch(monkeypatch):
    """reconstruct_scan reads segment.learned_cnn as the stage does; segment_tumor given a
    U-Net with learned_cnn off keeps the forest alone; another value is refused."""
    import tumor3d
    from tumor3d.learned import shipped
    from tumor3d.learned.cnn import unet_from_bytes, unet_volume_probability
    from tumor3d.segmentation.segment import segment_tumor

    net = unet_from_bytes(_tiny_unet_bytes(2))
    monkeypatch.setattr(shipped, "shipped_cnn", lambda m: net if m.lower() == "flair" else None)
    scan = make_phantom_patient(4, modality="flair", n_slices=10, matrix_size=(96, 96)).scan
    auto = tumor3d.reconstruct_scan(scan)
    off = tumor3d.reconstruct_scan(scan, config={"segment": {"learned_cnn": "off"}})
    p_net = unet_volume_probability(net, scan.image)
    assert auto.method == off.method == "learned"
    np.testing.assert_allclose(
        auto.tumor_probability, 0.5 * (off.tumor_probability + p_net), atol=1e-6
    )
    # the core: a U-Net handed over with learned_cnn off is not used
    from tumor3d.learned.cnn import unet_member_probabilities

    calls = []
    real = unet_member_probabilities
    monkeypatch.setattr(
        "tumor3d.learned.segment.unet_member_probabilities",
        lambda *a, **k: calls.append(1) or real(*a, **k),
    )
    from tumor3d.segmentation.detect import SliceDetection

    shape = scan.shape
    det = SliceDetection.from_records(
        [
            {"slice_index": z, "n_modes": 3, "abnormal": False, "peaks_gray": [], "brain_pixels": 0}
            for z in range(shape[0])
        ]
    )
    kw = dict(modality="flair", method="learned", image=scan.image, cnn=net)
    kw["model"] = shipped.shipped_model("flair")
    args = (np.zeros(shape, np.uint8), np.ones(shape, bool), det)
    with pytest.raises(InputError, match="learned_cnn must be"):
        segment_tumor(*args, learned_cnn="on", **kw)
    segment_tumor(*args, learned_cnn="off", **kw)
    assert calls == []
    segment_tumor(*args, learned_cnn="auto", **kw)
    assert calls == [1]
