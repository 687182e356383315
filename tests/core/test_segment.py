"""Tests of tumor3d.segmentation.segment (specification section 3)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from simple_phantom import FLAIR_INTENSITY, make_head_phantom

from tumor3d.config import DetectConfig, PreprocessConfig, SegmentConfig
from tumor3d.errors import InputError
from tumor3d.imaging.preprocess import preprocess_volume
from tumor3d.segmentation.detect import SliceDetection, detect_abnormal_slices
from tumor3d.segmentation.segment import fcm_memberships, fuzzy_cmeans_histogram, segment_tumor

DEFAULTS = SegmentConfig().model_dump()
FCM_DEFAULTS = {k: DEFAULTS[k] for k in ("fuzziness", "tol", "max_num_iter")}


def _dice(a: np.ndarray, b: np.ndarray) -> float:
    return 2.0 * np.count_nonzero(a & b) / (np.count_nonzero(a) + np.count_nonzero(b))


def _run(image):
    pre = preprocess_volume(image, **PreprocessConfig().model_dump())
    det = detect_abnormal_slices(pre.enhanced, pre.brain_mask, **DetectConfig().model_dump())
    return pre, det


@pytest.fixture(scope="module")
def t2_case():
    ph = make_head_phantom(tumor=True, seed=3)
    return (ph, *_run(ph.image))


@pytest.fixture(scope="module")
def flair_case():
    ph = make_head_phantom(tumor=True, seed=4, intensities=FLAIR_INTENSITY)
    return (ph, *_run(ph.image))


# --------------------------------------------------------------------------- FCM


def _mixture_hist(means, sigmas, weights, n, seed=0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    counts = rng.multinomial(n, np.asarray(weights) / np.sum(weights))
    parts = [rng.normal(m, s, c) for m, s, c in zip(means, sigmas, counts, strict=True)]
    pixels = np.clip(np.rint(np.concatenate(parts)), 0, 255).astype(np.int64)
    return np.bincount(pixels, minlength=256).astype(float), pixels


def _naive_fcm(pixels, v0, m, tol, max_num_iter):
    """Bezdek's FCM on the individual pixels (no histogram), textbook formulas."""
    x = pixels.astype(float)
    v = np.asarray(v0, dtype=float).copy()
    for _ in range(max_num_iter):
        d = np.abs(x[None, :] - v[:, None])  # (C, N); v0 is chosen off the integer grid
        u = 1.0 / np.sum((d[:, None, :] / d[None, :, :]) ** (2.0 / (m - 1.0)), axis=1)
        w = u**m
        v_new = (w @ x) / w.sum(axis=1)
        done = np.max(np.abs(v_new - v)) < tol
        v = v_new
        if done:
            break
    return v


def test_fcm_converges_to_component_means():
    means = (60.0, 130.0, 210.0)
    hist, _ = _mixture_hist(means, (6, 6, 6), (0.5, 0.3, 0.2), 50_000)
    v, diag = fuzzy_cmeans_histogram(
        hist, [40.5, 120.5, 230.5], **FCM_DEFAULTS, return_diagnostics=True
    )
    np.testing.assert_allclose(v, means, atol=2.0)
    assert diag.converged and 1 <= diag.n_iter < 100
    assert diag.objective.size == diag.n_iter
    assert np.all(np.diff(diag.objective) <= 1e-9 * diag.objective[0])  # FCM never increases J


def test_histogram_fcm_equals_pixel_fcm():
    hist, pixels = _mixture_hist((50, 100, 180, 220), (8, 10, 6, 9), (0.4, 0.3, 0.2, 0.1), 4000)
    v0 = [30.3, 90.7, 170.1, 240.9]
    for m in (1.5, 2.0, 3.0):
        fast = fuzzy_cmeans_histogram(hist, v0, fuzziness=m, tol=1e-8, max_num_iter=500)
        naive = _naive_fcm(pixels, v0, m, tol=1e-8, max_num_iter=500)
        np.testing.assert_allclose(fast, naive, atol=1e-6)


def test_memberships_sum_to_one_and_are_crisp_at_centres():
    g = np.arange(256.0)
    u = fcm_memberships(g, [20.0, 100.0, 200.0], 2.0)
    np.testing.assert_allclose(u.sum(axis=0), 1.0)
    np.testing.assert_array_equal(u[:, 100], [0.0, 1.0, 0.0])
    # argmax membership = nearest centre in 1-D
    nearest = np.argmin(np.abs(g - np.array([[20.0], [100.0], [200.0]])), axis=0)
    np.testing.assert_array_equal(np.argmax(u, axis=0), nearest)
    # m close to 1 must not overflow
    assert np.all(np.isfinite(fcm_memberships(g, [20.0, 100.0], 1.01)))


def test_fcm_leaves_its_input_unchanged():
    hist, _ = _mixture_hist((60, 200), (5, 5), (0.5, 0.5), 1000)
    seeds = np.array([50.0, 190.0])
    h0, s0 = hist.copy(), seeds.copy()
    fuzzy_cmeans_histogram(hist, seeds, **FCM_DEFAULTS)
    np.testing.assert_array_equal(hist, h0)
    np.testing.assert_array_equal(seeds, s0)


def test_fcm_rejects_empty_histogram():
    with pytest.raises(InputError, match="not all zero"):
        fuzzy_cmeans_histogram(np.zeros(256), [10.0], **FCM_DEFAULTS)


def test_fcm_rejects_bad_fuzziness():
    with pytest.raises(InputError, match="fuzziness"):
        fuzzy_cmeans_histogram(np.ones(256), [10.0], **{**FCM_DEFAULTS, "fuzziness": 1.0})


def test_fcm_rejects_no_centres():
    with pytest.raises(InputError, match="centers_init"):
        fuzzy_cmeans_histogram(np.ones(256), [], **FCM_DEFAULTS)


# --------------------------------------------------------------------------- segmentation


def test_segments_the_planted_blob(t2_case):
    ph, pre, det = t2_case
    res = segment_tumor(pre.enhanced, pre.brain_mask, det, modality="t2", **DEFAULTS)
    blob = ph.tumor.sum(axis=(1, 2))
    large = np.flatnonzero(blob >= 100)
    assert large.size == 4 and det.abnormal[large].all()
    for z in large:
        assert _dice(res.tumor_mask[z], ph.tumor[z]) > 0.85, z
        assert res.selection[z] == "reference"
    # nothing outside the abnormal slices, N_i = mask sums
    assert not res.tumor_mask[~det.abnormal].any()
    np.testing.assert_array_equal(res.tumor_pixels, res.tumor_mask.sum(axis=(1, 2)))
    assert res.tumor_pixels.dtype == np.int64
    # references ascend (WM < GM < CSF on T2) and the tumour lies between GM and CSF
    r = res.reference_centers
    assert np.all(np.diff(r) > 0)
    assert np.all((res.tumor_center_gray[large] > r[1]) & (res.tumor_center_gray[large] < r[2]))
    assert np.all(np.isnan(res.tumor_center_gray[~det.abnormal]))


def test_tumour_free_phantom_gives_empty_masks():
    ph = make_head_phantom(tumor=False, seed=3)
    pre, det = _run(ph.image)
    res = segment_tumor(pre.enhanced, pre.brain_mask, det, modality="t2", **DEFAULTS)
    assert res.tumor_pixels.sum() == 0


def test_t2_fallback_without_normal_slices(t2_case):
    ph, pre, det = t2_case
    keep = np.flatnonzero(det.abnormal)  # only abnormal slices: no reference
    sub = SliceDetection.from_records(
        [{**det.to_records()[z], "slice_index": i} for i, z in enumerate(keep)]
    )
    res = segment_tumor(pre.enhanced[keep], pre.brain_mask[keep], sub, modality="t2", **DEFAULTS)
    assert np.all(np.isnan(res.reference_centers))
    assert np.all(res.selection == "rule")  # second-brightest cluster on T2
    for i, z in enumerate(keep):
        assert _dice(res.tumor_mask[i], ph.tumor[z]) > 0.85


def test_flair_with_reference_and_with_the_brightest_rule(flair_case):
    ph, pre, det = flair_case
    large = np.flatnonzero(ph.tumor.sum(axis=(1, 2)) >= 100)
    assert det.abnormal[large].all()
    res = segment_tumor(pre.enhanced, pre.brain_mask, det, modality="FLAIR", **DEFAULTS)
    for z in large:
        assert _dice(res.tumor_mask[z], ph.tumor[z]) > 0.85
    # no slice outside the blob gets a tumour (implausible clusters are rejected)
    assert not res.tumor_mask[ph.tumor.sum(axis=(1, 2)) == 0].any()

    sub = SliceDetection.from_records(
        [{**det.to_records()[z], "slice_index": i} for i, z in enumerate(large)]
    )
    rule = segment_tumor(
        pre.enhanced[large], pre.brain_mask[large], sub, modality="flair", method="paper"
    )
    assert np.all(rule.selection == "rule")  # brightest cluster on FLAIR
    for i, z in enumerate(large):
        assert _dice(rule.tumor_mask[i], ph.tumor[z]) > 0.85


def test_paper_method_says_when_the_tumour_reaches_the_end_of_the_scan(flair_case):
    ph, pre, det = flair_case
    whole = segment_tumor(pre.enhanced, pre.brain_mask, det, modality="flair", method="paper")
    assert whole.tumor_mask.any() and whole.caveats == ()  # the tumour lies inside the head
    # the same head scanned only over the tumour's large slices: it fills the first and last
    large = np.flatnonzero(ph.tumor.sum(axis=(1, 2)) >= 100)
    sub = SliceDetection.from_records(
        [{**det.to_records()[z], "slice_index": i} for i, z in enumerate(large)]
    )
    cut = segment_tumor(
        pre.enhanced[large], pre.brain_mask[large], sub, modality="flair", method="paper"
    )
    assert cut.tumor_mask[0].any() and cut.tumor_mask[-1].any()
    assert len(cut.caveats) == 1
    assert f"first and last slices of the scan (slices 0 and {large.size - 1}" in cut.caveats[0]


def test_normal_slice_flagged_abnormal_gets_no_tumour(t2_case):
    ph, pre, det = t2_case
    normal = [z for z in range(len(det)) if not det.abnormal[z] and det.n_modes[z] == 3]
    flagged = det.abnormal.copy()
    flagged[normal[:2]] = True  # two tumour-free slices wrongly flagged, k = 3
    wrong = SliceDetection(
        n_modes=det.n_modes,
        abnormal=flagged,
        peaks_gray=det.peaks_gray,
        brain_pixels=det.brain_pixels,
    )
    res = segment_tumor(pre.enhanced, pre.brain_mask, wrong, modality="t2", **DEFAULTS)
    # its WM, GM and CSF clusters all match the references: no tumour there
    assert res.tumor_pixels[normal[:2]].sum() == 0
    assert set(res.selection[normal[:2]]) == {"none"}
    for z in np.flatnonzero(ph.tumor.sum(axis=(1, 2)) >= 100):
        assert _dice(res.tumor_mask[z], ph.tumor[z]) > 0.85


def test_min_tumor_pixels_drops_small_components(t2_case):
    _, pre, det = t2_case
    res = segment_tumor(
        pre.enhanced, pre.brain_mask, det, **{**DEFAULTS, "min_tumor_pixels": 10**6}
    )
    assert res.tumor_pixels.sum() == 0
    assert set(res.selection[det.abnormal]) == {"none"}


def test_mask_is_one_filled_4_connected_component(t2_case):
    from scipy import ndimage as ndi

    _, pre, det = t2_case
    res = segment_tumor(pre.enhanced, pre.brain_mask, det, **DEFAULTS)
    for z in np.flatnonzero(res.tumor_pixels):
        _, n = ndi.label(res.tumor_mask[z])  # 4-connectivity
        assert n == 1
        np.testing.assert_array_equal(ndi.binary_fill_holes(res.tumor_mask[z]), res.tumor_mask[z])


def test_records(t2_case):
    _, pre, det = t2_case
    res = segment_tumor(pre.enhanced, pre.brain_mask, det, **DEFAULTS)
    records = json.loads(json.dumps(res.to_records()))
    assert [r["slice_index"] for r in records] == list(range(len(det)))
    assert [r["tumor_pixels"] for r in records] == res.tumor_pixels.tolist()
    for r, c in zip(records, res.tumor_center_gray, strict=True):
        assert (r["tumor_center_gray"] is None) == bool(np.isnan(c))


def test_inputs_unchanged(t2_case):
    _, pre, det = t2_case
    img, mask = pre.enhanced.copy(), pre.brain_mask.copy()
    records = det.to_records()
    segment_tumor(img, mask, det, **DEFAULTS)
    np.testing.assert_array_equal(img, pre.enhanced)
    np.testing.assert_array_equal(mask, pre.brain_mask)
    assert det.to_records() == records


# --------------------------------------------------------------------------- validation


def test_rejects_wrong_ndim(t2_case):
    _, pre, det = t2_case
    with pytest.raises(InputError, match="3-D"):
        segment_tumor(pre.enhanced[0], pre.brain_mask[0], det, **DEFAULTS)


def test_rejects_shape_mismatch(t2_case):
    _, pre, det = t2_case
    with pytest.raises(InputError, match="does not match"):
        segment_tumor(pre.enhanced, pre.brain_mask[:, 1:], det, **DEFAULTS)


def test_rejects_detection_of_other_length(t2_case):
    _, pre, det = t2_case
    with pytest.raises(InputError, match="detection has"):
        segment_tumor(pre.enhanced[1:], pre.brain_mask[1:], det, **DEFAULTS)


def test_rejects_unknown_modality(t2_case):
    _, pre, det = t2_case
    with pytest.raises(InputError, match="unknown modality"):
        segment_tumor(pre.enhanced, pre.brain_mask, det, modality="dwi", **DEFAULTS)


def test_rejects_unknown_wavelet(t2_case):
    _, pre, det = t2_case
    with pytest.raises(InputError, match="wavelet"):
        segment_tumor(pre.enhanced, pre.brain_mask, det, **{**DEFAULTS, "wavelet": "db2"})


@pytest.mark.parametrize(
    ("name", "value", "why"),
    [
        ("min_tumor_pixels", 0, "min_tumor_pixels must be >= 1, got 0"),
        ("min_tumor_slices", 0, "min_tumor_slices must be >= 1, got 0"),
        ("max_brain_fraction", 1.5, r"max_brain_fraction must lie in \(0, 1\], got 1.5"),
        ("max_brain_fraction", 0.0, r"max_brain_fraction must lie in \(0, 1\], got 0.0"),
        ("rim_px", -1, "rim_px must be >= 0, got -1"),
        ("component_tolerance_px", -2, "component_tolerance_px must be >= 0, got -2"),
        ("fuzziness", 1.0, "fuzziness"),
    ],
)
def test_the_paper_method_names_a_parameter_out_of_range(t2_case, name, value, why):
    _, pre, det = t2_case
    bad = {**DEFAULTS, "method": "paper", name: value}
    with pytest.raises(InputError, match=why):
        segment_tumor(pre.enhanced, pre.brain_mask, det, **bad)


def test_the_paper_method_takes_its_parameters_as_their_types(t2_case):
    """Whole numbers given as floats (a YAML ``5.0``) run as the integers they are."""
    _, pre, det = t2_case
    given = {**DEFAULTS, "method": "paper"}
    as_float = {k: float(given[k]) for k in ("min_tumor_pixels", "rim_px", "max_num_iter")}
    a = segment_tumor(pre.enhanced, pre.brain_mask, det, **given)
    b = segment_tumor(pre.enhanced, pre.brain_mask, det, **{**given, **as_float})
    np.testing.assert_array_equal(a.tumor_mask, b.tumor_mask)


def test_rejects_non_gray_image(t2_case):
    _, pre, det = t2_case
    with pytest.raises(InputError, match="whole gray levels"):
        segment_tumor(pre.enhanced + 0.5, pre.brain_mask, det, **DEFAULTS)


def test_rejects_non_detection(t2_case):
    _, pre, _ = t2_case
    with pytest.raises(InputError, match="SliceDetection"):
        segment_tumor(pre.enhanced, pre.brain_mask, {"abnormal": []}, **DEFAULTS)


# --------------------------------------------------------------------------- robust method and peer


def _flair_robust(seed: int, tumor: bool = True):
    ph = make_head_phantom(tumor=tumor, seed=seed, intensities=FLAIR_INTENSITY)
    pre = preprocess_volume(ph.image, **PreprocessConfig().model_dump())
    det = detect_abnormal_slices(
        pre.enhanced, pre.brain_mask, modality="flair", **DetectConfig().model_dump()
    )
    res = segment_tumor(pre.enhanced, pre.brain_mask, det, modality="flair", **DEFAULTS)
    return ph, det, res


def test_robust_default_on_flair_finds_every_blob_slice_and_nothing_else():
    ph, det, res = _flair_robust(5)
    truth_slices = ph.tumor.any(axis=(1, 2))
    assert np.array_equal(det.abnormal, truth_slices)
    assert _dice(res.tumor_mask, ph.tumor) > 0.97
    assert set(res.selection[truth_slices]) == {"lesion"}
    rec = res.to_records()[0]
    assert rec["fcm_iterations"] == -1 and rec["fcm_converged"] is False


def test_robust_default_on_tumour_free_flair_is_empty():
    # the phantom's bimodal parenchyma puts grey matter "outside" the median / MAD
    # model; a lesion covering most of the brain is rejected (MAX_BRAIN_FRACTION)
    _, det, res = _flair_robust(6, tumor=False)
    assert not det.abnormal.any()
    assert res.tumor_pixels.sum() == 0


def test_multiotsu_peer_segments_the_flair_blob():
    ph = make_head_phantom(tumor=True, seed=7, intensities=FLAIR_INTENSITY)
    pre = preprocess_volume(ph.image, **PreprocessConfig().model_dump())
    det = detect_abnormal_slices(pre.enhanced, pre.brain_mask)
    res = segment_tumor(
        pre.enhanced, pre.brain_mask, det, modality="flair", **{**DEFAULTS, "method": "multiotsu"}
    )
    assert _dice(res.tumor_mask, ph.tumor) > 0.8
    assert set(res.selection[res.tumor_pixels > 0]) == {"multiotsu"}


def test_auto_method_resolves_by_modality():
    from tumor3d.segmentation.segment import resolve_method

    # the learned method on FLAIR and T1c: chosen by cross-validation (reports/learned_cv.md)
    assert resolve_method("auto", "FLAIR") == "learned"
    assert resolve_method("auto", "t1c") == "learned"
    assert resolve_method("auto", "t2") == "paper"
    assert resolve_method("multiotsu", "t2") == "multiotsu"


def test_rejects_unknown_method(t2_case):
    _, pre, det = t2_case
    with pytest.raises(InputError, match="method"):
        segment_tumor(pre.enhanced, pre.brain_mask, det, method="kmeans")
    with pytest.raises(InputError, match="method"):
        detect_abnormal_slices(pre.enhanced, pre.brain_mask, method="kmeans")


def test_robust_on_a_brain_without_any_tissue_contrast_is_empty():
    brain = np.zeros((3, 40, 40), dtype=bool)
    brain[:, 5:35, 5:35] = True
    enhanced = np.where(brain, 120, 0).astype(np.uint8)
    det = detect_abnormal_slices(enhanced, brain, modality="flair", min_brain_pixels=0)
    res = segment_tumor(enhanced, brain, det, modality="flair", method="robust")
    assert not det.abnormal.any() and res.tumor_pixels.sum() == 0


def test_histogram_fcm_matches_naive_pixel_fcm_of_tumor3d_fcm():
    from tumor3d.segmentation.fcm import fuzzy_cmeans_pixels

    rng = np.random.default_rng(2)
    pixels = np.clip(np.concatenate([rng.normal(m, 6, 300) for m in (60, 120, 200)]), 0, 255)
    pixels = np.round(pixels)
    hist = np.bincount(pixels.astype(int), minlength=256)
    v0 = np.array([50.0, 130.0, 190.0])
    v_hist = fuzzy_cmeans_histogram(hist, v0, tol=1e-6, max_num_iter=500)
    v_pix = fuzzy_cmeans_pixels(pixels, v0, tol=1e-6, max_num_iter=500)
    np.testing.assert_allclose(v_hist, v_pix, atol=1e-3)


@pytest.mark.parametrize(
    "method, modality, words",
    [
        ("robust", "flair", "FLAIR-hyperintense lesion"),
        ("robust", "t2", "T2-hyperintense lesion"),
        ("robust", "t1c", "contrast-enhancing lesion with its enclosed necrotic core (no oedema)"),
        ("paper", "t2", "fuzzy c-means segmentation (Arakeri & Reddy 2013, section 3) on T2"),
        ("multiotsu", "flair", "multi-Otsu classes of the brain on FLAIR"),
    ],
)
def test_lesion_definition_names_what_each_method_measures(method, modality, words):
    from tumor3d.segmentation.segment import lesion_definition

    assert words in lesion_definition(method, modality)
    assert ("oedema" in lesion_definition(method, modality)) == (method == "robust")


def test_lesion_definition_refuses_an_unresolved_method_or_unknown_modality():
    from tumor3d.segmentation.segment import lesion_definition

    with pytest.raises(InputError, match="no definition for method 'auto'"):
        lesion_definition("auto", "flair")
    with pytest.raises(InputError, match="unknown modality 't1'"):
        lesion_definition("robust", "t1")


@pytest.mark.parametrize(
    "case, modality, method, expected",
    [
        ("t2_case", "t2", "auto", "paper"),  # the T2 phantoms: the paper's premise holds
        ("flair_case", "flair", "auto", "robust"),
        ("flair_case", "flair", "multiotsu", "multiotsu"),
    ],
)
def test_the_result_names_the_method_that_ran(request, case, modality, method, expected):
    _, pre, det = request.getfixturevalue(case)
    res = segment_tumor(
        pre.enhanced, pre.brain_mask, det, modality=modality, **{**DEFAULTS, "method": method}
    )
    assert res.method == expected and res.tumor_pixels.sum() > 0
