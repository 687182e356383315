"""Tests of tumor3d.segmentation.detect (specification section 2)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from simple_phantom import make_head_phantom

from tumor3d.config import DetectConfig, PreprocessConfig
from tumor3d.errors import InputError
from tumor3d.imaging.preprocess import preprocess_volume
from tumor3d.segmentation.detect import (
    SliceDetection,
    count_histogram_modes,
    detect_abnormal_slices,
)

DEFAULTS = DetectConfig().model_dump()
MODE_KEYS = ("n_bins", "smoothing_sigma_bins", "min_mode_area", "min_peak_distance_bins")
MODE_DEFAULTS = {k: DEFAULTS[k] for k in (*MODE_KEYS, "min_valley_significance")}


def _mixture(means, sigmas, weights, n, seed=0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    counts = rng.multinomial(n, np.asarray(weights) / np.sum(weights))
    parts = [rng.normal(m, s, c) for m, s, c in zip(means, sigmas, counts, strict=True)]
    return np.clip(np.rint(np.concatenate(parts)), 0, 255).astype(np.uint8)


@pytest.fixture(scope="module")
def tumour_volume():
    ph = make_head_phantom(tumor=True, seed=2)
    return ph, preprocess_volume(ph.image, **PreprocessConfig().model_dump())


@pytest.fixture(scope="module")
def normal_volume():
    ph = make_head_phantom(tumor=False, seed=2)
    return ph, preprocess_volume(ph.image, **PreprocessConfig().model_dump())


# --------------------------------------------------------------------------- mode counting


@pytest.mark.parametrize(
    ("means", "weights"),
    [
        ((60, 130, 220), (0.5, 0.3, 0.2)),  # three tissues
        ((60, 130, 180, 230), (0.45, 0.3, 0.1, 0.15)),  # plus a tumour
    ],
)
def test_counts_modes_of_known_mixture(means, weights):
    values = _mixture(means, [6] * len(means), weights, 30_000)
    modes = count_histogram_modes(values, **MODE_DEFAULTS)
    assert modes.n_modes == len(means)
    # peaks at the component means, within one 4-level bin
    np.testing.assert_allclose(modes.peaks_gray, means, atol=4.0)
    np.testing.assert_allclose(modes.areas, weights, atol=0.03)
    assert modes.areas.sum() == pytest.approx(1.0)


def test_tiny_mode_below_min_area_is_merged():
    plain = {**MODE_DEFAULTS, "min_valley_significance": 0.0}
    values = _mixture((60, 130, 220, 250), (5, 5, 5, 1), (0.5, 0.3, 0.198, 0.002), 50_000)
    merged = count_histogram_modes(values, **{**plain, "min_mode_area": 0.005})
    kept = count_histogram_modes(values, **{**plain, "min_mode_area": 0.0})
    assert kept.n_modes == 4  # the 0.2 % mode is a real, separate peak ...
    assert merged.n_modes == 3  # ... removed only by the area rule
    # it went to its only neighbour, the CSF-like mode at 220, which kept its peak
    assert merged.peaks_gray[-1] == pytest.approx(kept.peaks_gray[2])
    assert merged.areas[-1] == pytest.approx(kept.areas[2] + kept.areas[3])


def test_close_peaks_are_merged():
    plain = {**MODE_DEFAULTS, "min_valley_significance": 0.0, "smoothing_sigma_bins": 0.0}
    values = _mixture((100, 110), (1.0, 1.0), (0.6, 0.4), 20_000)  # bins 25 and 27
    assert count_histogram_modes(values, **{**plain, "min_peak_distance_bins": 0}).n_modes == 2
    merged = count_histogram_modes(values, **{**plain, "min_peak_distance_bins": 3})
    assert merged.n_modes == 1
    assert abs(merged.peaks_gray[0] - 100) <= 2  # the higher (60 %) peak survives


def test_noise_bumps_of_a_sparse_histogram_are_not_modes():
    # 400 pixels spread evenly over 150 gray levels: a single flat mode
    rng = np.random.default_rng(11)
    values = rng.integers(50, 200, size=400).astype(np.uint8)
    plain = count_histogram_modes(values, **{**MODE_DEFAULTS, "min_valley_significance": 0.0})
    tested = count_histogram_modes(values, **MODE_DEFAULTS)
    assert plain.n_modes >= 4  # the [A5] area/distance rules alone keep noise bumps
    assert tested.n_modes == 1


def test_plateau_peak_is_at_its_centre():
    values = np.repeat(np.arange(100, 140, dtype=np.uint8), 50)  # flat 100..139 = bins 25..34
    modes = count_histogram_modes(values, **{**MODE_DEFAULTS, "smoothing_sigma_bins": 0.0})
    assert modes.n_modes == 1
    assert modes.peaks_gray[0] == pytest.approx((25 + 34) / 2 * 4 + 1.5)


def test_empty_values_have_no_mode():
    modes = count_histogram_modes(np.zeros(0, dtype=np.uint8), **MODE_DEFAULTS)
    assert modes.n_modes == 0 and modes.peaks_gray.size == 0


@settings(max_examples=25, deadline=None)
@given(
    k=st.integers(1, 5),
    gaps=st.lists(st.integers(40, 60), min_size=4, max_size=4),
    sigma=st.floats(2.0, 6.0),
    raw_weights=st.lists(st.floats(1.0, 4.0), min_size=5, max_size=5),
    seed=st.integers(0, 2**16),
)
def test_well_separated_random_mixtures(k, gaps, sigma, raw_weights, seed):
    means = 20 + np.concatenate([[0], np.cumsum(gaps[: k - 1])])
    weights = np.array(raw_weights[:k]) / np.sum(raw_weights[:k])  # each >= 1/13 of the mass
    values = _mixture(means, [sigma] * k, weights, 20_000, seed=seed)
    modes = count_histogram_modes(values, **MODE_DEFAULTS)
    assert modes.n_modes == k
    np.testing.assert_allclose(modes.peaks_gray, means, atol=4.0)


# --------------------------------------------------------------------------- per-slice detection


def test_blob_slices_are_abnormal(tumour_volume):
    ph, pre = tumour_volume
    det = detect_abnormal_slices(pre.enhanced, pre.brain_mask, **DEFAULTS)
    has_blob = ph.tumor.sum(axis=(1, 2)) >= 100  # slices 4-7, 137-241 px
    assert has_blob.sum() == 4
    np.testing.assert_array_equal(det.abnormal, has_blob)
    assert np.all(det.n_modes[~has_blob] <= 3)
    assert np.all(det.n_modes[has_blob] == 4)
    np.testing.assert_array_equal(det.brain_pixels, pre.brain_mask.sum(axis=(1, 2)))
    # the seeds are sorted peak gray levels, one per mode
    for z, peaks in enumerate(det.peaks_gray):
        assert peaks.size == det.n_modes[z]
        assert np.all(np.diff(peaks) > 0)


def test_normal_phantom_has_no_abnormal_slice(normal_volume):
    _, pre = normal_volume
    det = detect_abnormal_slices(pre.enhanced, pre.brain_mask, **DEFAULTS)
    assert not det.abnormal.any()
    assert np.all(det.n_modes == 3)  # WM, GM, CSF


def test_histogram_ignores_pixels_outside_the_brain(tumour_volume):
    _, pre = tumour_volume
    noisy = pre.enhanced.copy()
    rng = np.random.default_rng(0)
    outside = ~pre.brain_mask
    noisy[outside] = rng.integers(0, 256, size=int(outside.sum()))
    a = detect_abnormal_slices(pre.enhanced, pre.brain_mask, **DEFAULTS)
    b = detect_abnormal_slices(noisy, pre.brain_mask, **DEFAULTS)
    np.testing.assert_array_equal(a.n_modes, b.n_modes)


def test_small_brains_are_never_abnormal(tumour_volume):
    _, pre = tumour_volume
    det = detect_abnormal_slices(
        pre.enhanced, pre.brain_mask, **{**DEFAULTS, "min_brain_pixels": 10**6}
    )
    assert not det.abnormal.any()
    assert np.any(det.n_modes >= 4)  # the modes are still counted


def test_inputs_unchanged(tumour_volume):
    _, pre = tumour_volume
    img, mask = pre.enhanced.copy(), pre.brain_mask.copy()
    detect_abnormal_slices(img, mask, **DEFAULTS)
    np.testing.assert_array_equal(img, pre.enhanced)
    np.testing.assert_array_equal(mask, pre.brain_mask)


def test_accepts_storage_dtypes(tumour_volume):
    _, pre = tumour_volume
    a = detect_abnormal_slices(pre.enhanced, pre.brain_mask, **DEFAULTS)
    b = detect_abnormal_slices(
        pre.enhanced.astype(np.float32), pre.brain_mask.astype(np.uint8), **DEFAULTS
    )
    np.testing.assert_array_equal(a.n_modes, b.n_modes)


# --------------------------------------------------------------------------- records


def test_records_round_trip_exactly(tumour_volume):
    _, pre = tumour_volume
    det = detect_abnormal_slices(pre.enhanced, pre.brain_mask, **DEFAULTS)
    records = det.to_records()
    assert [r["slice_index"] for r in records] == list(range(len(det)))
    via_json = json.loads(json.dumps(records))
    back = SliceDetection.from_records(list(reversed(via_json)))
    np.testing.assert_array_equal(back.n_modes, det.n_modes)
    np.testing.assert_array_equal(back.abnormal, det.abnormal)
    np.testing.assert_array_equal(back.brain_pixels, det.brain_pixels)
    for p, q in zip(back.peaks_gray, det.peaks_gray, strict=True):
        np.testing.assert_array_equal(p, q)
    assert back.to_records() == records


def test_from_records_rejects_missing_key():
    with pytest.raises(InputError, match="lacks key"):
        SliceDetection.from_records([{"slice_index": 0, "n_modes": 3}])


def test_from_records_rejects_gaps_in_slice_indices():
    row = {"n_modes": 3, "abnormal": False, "peaks_gray": [1.0], "brain_pixels": 9}
    with pytest.raises(InputError, match="slice_index"):
        SliceDetection.from_records([{**row, "slice_index": 0}, {**row, "slice_index": 2}])


def test_detection_fields_must_agree_in_length():
    with pytest.raises(InputError, match="one entry per slice"):
        SliceDetection(n_modes=[3, 4], abnormal=[False], peaks_gray=((), ()), brain_pixels=[1, 2])


# --------------------------------------------------------------------------- validation


def test_rejects_wrong_ndim():
    with pytest.raises(InputError, match="3-D"):
        detect_abnormal_slices(np.zeros((4, 4), np.uint8), np.ones((4, 4), bool), **DEFAULTS)


def test_rejects_shape_mismatch():
    with pytest.raises(InputError, match="does not match"):
        detect_abnormal_slices(np.zeros((2, 4, 4), np.uint8), np.ones((2, 4, 5), bool), **DEFAULTS)


def test_rejects_non_gray_levels():
    with pytest.raises(InputError, match="whole gray levels"):
        detect_abnormal_slices(np.full((1, 4, 4), 0.5), np.ones((1, 4, 4), bool), **DEFAULTS)


def test_rejects_non_boolean_mask():
    with pytest.raises(InputError, match="brain_mask must be boolean"):
        detect_abnormal_slices(np.zeros((1, 4, 4), np.uint8), np.full((1, 4, 4), 2), **DEFAULTS)


def test_count_rejects_float_values():
    with pytest.raises(InputError, match="integer gray levels"):
        count_histogram_modes(np.array([1.5, 2.0]), **MODE_DEFAULTS)


def test_count_rejects_out_of_range_values():
    with pytest.raises(InputError, match="0-255"):
        count_histogram_modes(np.array([3, 300]), **MODE_DEFAULTS)


def test_rejects_bad_n_bins():
    with pytest.raises(InputError, match="n_bins"):
        count_histogram_modes(np.arange(10, dtype=np.uint8), **{**MODE_DEFAULTS, "n_bins": 1})


def test_rejects_negative_significance():
    with pytest.raises(InputError, match="min_valley_significance"):
        count_histogram_modes(
            np.arange(10, dtype=np.uint8), **{**MODE_DEFAULTS, "min_valley_significance": -1}
        )


@pytest.mark.parametrize("pixel_mm", [0.5, 1.0, 2.0])
def test_a_robust_slice_is_abnormal_by_its_lesion_area_in_mm2(monkeypatch, pixel_mm):
    # the lesion model's mask is given (its own tests are in test_lesion.py): slices 1-3
    # hold 8, 32 and 96 mm2 of lesion against lesion_min_slice_mm2 = 20. At 0.5 and 1 mm
    # pixels the rule is that area (at 0.5 mm 32 and 128 pixels: a count in pixels would
    # flag slice 1 too); at 2 mm pixels it is the 20 pixels it has at 1 mm (80 mm2):
    # 2, 8 and 24 pixels flag slice 3 only
    import tumor3d.segmentation.detect as detect_module
    from tumor3d.segmentation.lesion import LesionResult, NormalModel

    n = int(round(64 / pixel_mm))
    shape = (5, n, n)
    lesion = np.zeros(shape, bool)
    for z, (h_mm, w_mm) in ((1, (4.0, 2.0)), (2, (8.0, 4.0)), (3, (16.0, 6.0))):
        h, w = int(round(h_mm / pixel_mm)), int(round(w_mm / pixel_mm))
        lesion[z, 10 : 10 + h, 10 : 10 + w] = True
        assert lesion[z].sum() * pixel_mm**2 == pytest.approx(h_mm * w_mm)

    def given_lesion(img, mask, **kw):
        model = NormalModel(100.0, 10.0, 120.0, float("inf"))
        return LesionResult(lesion, model, 150.0, 125.0, 1)

    monkeypatch.setattr(detect_module, "patient_lesion", given_lesion)
    brain = np.ones(shape, bool)
    img = np.full(shape, 100, np.uint8)
    det = detect_abnormal_slices(
        img, brain, method="robust", modality="flair", min_brain_pixels=0,
        lesion_min_slice_mm2=20.0, spacing_mm=(5.0, pixel_mm, pixel_mm),
    )  # fmt: skip
    expected = [False, False, True, True, False] if pixel_mm <= 1.0 else [False] * 3 + [True, False]
    assert det.abnormal.tolist() == expected
