"""Tests of the documented robustness rules that extend the paper's method.

Each test pins one rule with an independent expectation (a small hand-built
array whose right answer is obvious, or the phantom's ground truth) and fails
if the rule is switched off:

- ``tumor3d.imaging.preprocess.skull._keep_nested_slices`` (scalp discs beyond the brain);
- ``tumor3d.segmentation.segment``: the T2 CSF pin and the populous-unmatched rule of
  ``_choose_tumor_cluster``, the brain rim of ``_tumor_component``,
  ``max_brain_fraction``, the 3-D grouping (``_largest_linked_group``),
  the tips (``_extend_tips``: partial volume, third tissue excluded) and
  ``_refine_boundary``;
- ``tumor3d.geometry.interpolate.interpolate_stack(..., end_caps="taper")``.
"""

from __future__ import annotations

import numpy as np
import pytest

from tumor3d.config import PipelineConfig
from tumor3d.errors import InputError
from tumor3d.geometry.interpolate import interpolate_pair, interpolate_stack
from tumor3d.geometry.surface import extract_surface, mesh_volume_mm3
from tumor3d.imaging.preprocess import preprocess_volume
from tumor3d.imaging.preprocess.skull import _keep_nested_slices
from tumor3d.phantom import make_phantom_patient
from tumor3d.segmentation.detect import SliceDetection
from tumor3d.segmentation.segment import (
    _choose_tumor_cluster,
    _largest_linked_group,
    _refine_boundary,
    _tumor_component,
    segment_tumor,
)

SCALP, CSF_LABEL, GM_LABEL, WM_LABEL, TUMOUR_LABEL = 1, 3, 4, 5, 6


def _disk(shape, centre, radius) -> np.ndarray:
    yy, xx = np.indices(shape)
    return np.hypot(yy - centre[0], xx - centre[1]) <= radius


# =========================================================================== preprocess


def test_nested_slices_clears_scalp_discs_and_everything_beyond():
    shape = (64, 64)
    c = (31.5, 31.5)
    # a head cut by slices 0-8: the brain widest on slice 4, scalp cut
    # tangentially into solid discs on slices 0 and 7 (the largest component
    # there), and a small component beyond the scalp disc on slice 8
    radii = [20, 7, 13, 18, 22, 17, 12, 21, 5]
    mask = np.stack([_disk(shape, c, r) for r in radii])
    before = mask.copy()
    out = _keep_nested_slices(mask)
    expected = mask.copy()
    # walking outwards from slice 4: slice 0 lies mostly outside slice 1
    # (r 7 + 3 px tolerance), slice 7 mostly outside slice 6: both are
    # cleared, and slice 8 beyond slice 7 too, although it is nested
    expected[0] = False
    expected[7:] = False
    np.testing.assert_array_equal(out, expected)
    np.testing.assert_array_equal(mask, before)  # input untouched


def test_nested_slices_keeps_the_brain_when_a_face_slice_is_the_widest():
    shape = (64, 64)
    c = (31.5, 31.5)
    # a raw head scanned from below the skull base: slices 0-1 cut the face and
    # neck, wider (r 26, 25) than any brain slice (widest r 22 on slice 7); slice 2
    # is a thin arc of scalp, and the brain's first slice (r 10) lies outside that
    # arc, so the walk from slice 0 stops at slice 3 and would clear the whole brain
    arc = _disk(shape, c, 26) & ~_disk(shape, c, 23) & (np.indices(shape)[0] < 20)
    brain_radii = [10, 14, 18, 20, 22, 21, 18, 15, 11, 6]
    mask = np.stack(
        [_disk(shape, c, 26), _disk(shape, c, 25), arc] + [_disk(shape, c, r) for r in brain_radii]
    )
    before = mask.copy()
    out = _keep_nested_slices(mask)
    expected = mask.copy()
    expected[:3] = False  # the walk from the brain's widest slice clears slice 2 and beyond
    np.testing.assert_array_equal(out, expected)
    np.testing.assert_array_equal(mask, before)  # input untouched


def test_nested_slices_leaves_a_normal_stack_alone():
    shape = (64, 64)
    # shrinking outwards, with a 1-pixel non-monotone wobble (slice 1 vs 2)
    # and an off-centre slice, all within the nesting tolerance
    specs = [
        ((31, 31), 6),
        ((31, 31), 12),
        ((31, 31), 11),
        ((31, 31), 17),
        ((31, 31), 20),
        ((32, 30), 18),
        ((33, 30), 14),
        ((33, 29), 8),
    ]
    mask = np.stack([_disk(shape, c, r) for c, r in specs])
    mask = np.concatenate([np.zeros((1,) + shape, dtype=bool), mask])  # empty end slice
    before = mask.copy()
    out = _keep_nested_slices(mask)
    np.testing.assert_array_equal(out, before)
    np.testing.assert_array_equal(mask, before)
    assert not _keep_nested_slices(np.zeros((3, 8, 8), dtype=bool)).any()


@pytest.fixture(scope="module", params=[0, 3, 5])
def phantom_preprocessed(request):
    patient = make_phantom_patient(request.param)
    pre = preprocess_volume(patient.scan.image, **PipelineConfig().preprocess.model_dump())
    return patient, pre


def test_phantom_brain_masks_hold_no_scalp(phantom_preprocessed):
    patient, pre = phantom_preprocessed
    labels = patient.tissue_labels
    scalp_px = np.count_nonzero(pre.brain_mask & (labels == SCALP), axis=(1, 2))
    assert scalp_px.tolist() == [0] * len(scalp_px)
    # the rule must not clear the brain itself: every slice whose true brain
    # cross-section is at least half the largest one keeps a brain mask that
    # covers most of it
    true_brain = np.isin(labels, [CSF_LABEL, GM_LABEL, WM_LABEL, TUMOUR_LABEL])
    area = true_brain.sum(axis=(1, 2))
    for z in np.flatnonzero(area >= 0.5 * area.max()):
        covered = np.count_nonzero(pre.brain_mask[z] & true_brain[z])
        assert covered >= 0.95 * area[z], z


# ================================================================ segment: cluster choice


def test_t2_csf_pin_never_takes_the_brightest_cluster():
    # CSF reference biased low (222) by partial volume: unpinned, the
    # assignment leaves the real CSF (254) unmatched.
    v = np.array([82.0, 126.0, 198.0, 254.0])
    ref = np.array([84.0, 130.0, 222.0])
    assert _choose_tumor_cluster(v, ref, "t2") == (2, "reference")
    # even when the brightest cluster is by far the most populous
    assert _choose_tumor_cluster(v, ref, "t2", np.array([900.0, 900, 300, 5000])) == (
        2,
        "reference",
    )
    # the pin is a T2 rule: on FLAIR the hyperintensity is the brightest cluster
    assert _choose_tumor_cluster(v, ref, "flair")[0] == 3


def test_most_populous_unmatched_cluster_is_the_tumour():
    v = np.array([83.0, 120.0, 162.0, 202.0, 250.0])
    ref = np.array([84.0, 130.0, 223.0])
    # measured on a phantom slice: 397 partial-volume pixels at 162, 1440
    # tumour pixels at 202; 162 lies farther from every reference
    mass = np.array([5200.0, 3100.0, 397.0, 1440.0, 900.0])
    assert _choose_tumor_cluster(v, ref, "t2", mass) == (3, "reference")
    # the mass decides, not the position: swap the populations
    swapped = mass.copy()
    swapped[[2, 3]] = swapped[[3, 2]]
    assert _choose_tumor_cluster(v, ref, "t2", swapped) == (2, "reference")


# =========================================================================== segment: rim


def test_rim_ring_along_the_brain_boundary_is_not_the_tumour():
    shape = (80, 80)
    c = (39.5, 39.5)
    brain = _disk(shape, c, 30)
    rim_ring = brain & ~_disk(shape, c, 28)  # 2-pixel partial-volume ring
    blob = _disk(shape, (35, 45), 5)  # small true tumour, deep inside
    cluster = rim_ring | blob
    assert rim_ring.sum() > 3 * blob.sum()  # the ring is the largest component
    out = _tumor_component(cluster, brain, 3)
    np.testing.assert_array_equal(out, blob)
    # the literal rule (rim_px = 0) fills the ring into a disc: the whole brain
    literal = _tumor_component(cluster, brain, 0)
    np.testing.assert_array_equal(literal, brain)


def test_blob_touching_the_cortex_keeps_its_boundary_pixels():
    shape = (80, 80)
    c = (39.5, 39.5)
    brain = _disk(shape, c, 30)
    cluster = brain & _disk(shape, (39.5, 64.0), 9)  # cut by the brain boundary
    rim_zone = brain & ~_disk(shape, c, 26.5)
    assert np.count_nonzero(cluster & rim_zone) > 50
    out = _tumor_component(cluster, brain, 3)
    np.testing.assert_array_equal(out, cluster)


# ============================================================== segment: synthetic stacks

N_PX = 96
WM, GM, TUMOUR, CSF = 80, 130, 180, 220
PEAKS_NORMAL = [float(WM), float(GM), float(CSF)]
PEAKS_ABNORMAL = [float(WM), float(GM), float(TUMOUR), float(CSF)]
CENTRE = ((N_PX - 1) / 2.0, (N_PX - 1) / 2.0)


def _brain_slice() -> tuple[np.ndarray, np.ndarray]:
    """Concentric WM (r < 26), GM (< 34) and CSF (< 40) and the brain mask."""
    yy, xx = np.indices((N_PX, N_PX))
    r = np.hypot(yy - CENTRE[0], xx - CENTRE[1])
    img = np.zeros((N_PX, N_PX), dtype=np.uint8)
    img[r < 40] = CSF
    img[r < 34] = GM
    img[r < 26] = WM
    return img, r < 40


def _synthetic_case(blobs: dict[int, list], abnormal: set[int], nz: int):
    """A stack of ``nz`` slices with tumour-gray regions and a hand-made detection.

    ``blobs[z]`` lists boolean regions painted with the tumour gray on slice
    ``z``; slices in ``abnormal`` get k = 4 with the four true peaks, the
    others k = 3 (WM, GM, CSF).
    """
    img = np.zeros((nz, N_PX, N_PX), dtype=np.uint8)
    brain = np.zeros(img.shape, dtype=bool)
    for z in range(nz):
        img[z], brain[z] = _brain_slice()
        for region in blobs.get(z, []):
            img[z][region & brain[z]] = TUMOUR
    flags = np.array([z in abnormal for z in range(nz)])
    detection = SliceDetection(
        n_modes=np.where(flags, 4, 3),
        abnormal=flags,
        peaks_gray=tuple(np.array(PEAKS_ABNORMAL if f else PEAKS_NORMAL) for f in flags),
        brain_pixels=brain.sum(axis=(1, 2)),
    )
    return img, brain, detection


def test_tumour_covering_most_of_the_brain_is_partial_volume():
    # a tumour-gray band (22 < r < 32) around WM: hole-filled it covers
    # (32/40)^2 = 64 % of the brain, like a slice cutting the surface tangentially
    yy, xx = np.indices((N_PX, N_PX))
    r = np.hypot(yy - CENTRE[0], xx - CENTRE[1])
    band = (r > 22) & (r < 32)
    img, brain, det = _synthetic_case({1: [band]}, {1}, 3)
    # one-slice object: min_tumor_slices=1 so that only the rule under test acts
    res = segment_tumor(img, brain, det, modality="t2", min_tumor_slices=1)  # fraction 0.5
    assert res.selection[1] == "partial-volume"
    assert not res.tumor_mask.any()
    assert res.tumor_pixels.tolist() == [0, 0, 0]
    # the same slice is accepted when the check allows 70 %: the filled disc
    # (boundary refinement off: it is not the rule under test here)
    loose = segment_tumor(
        img,
        brain,
        det,
        modality="t2",
        max_brain_fraction=0.7,
        refine_boundary=False,
        min_tumor_slices=1,
    )
    assert loose.selection[1] == "reference"
    np.testing.assert_array_equal(loose.tumor_mask[1], r < 32)


def _drift_blob(z: int) -> np.ndarray:
    # radius 5, 12 px drift per slice: a 1-pixel gap between consecutive slices
    return _disk((N_PX, N_PX), (47.5, 36.0 + 12.0 * (z - 3)), 5)


def test_largest_linked_group_links_a_drifting_tumour_and_drops_a_distant_group():
    nz = 10
    tumor = np.zeros((nz, N_PX, N_PX), dtype=bool)
    for z in (3, 4, 5):
        tumor[z] = _drift_blob(z)
    # consecutive masks do not overlap, they are only 1 pixel apart
    assert not np.any(tumor[3] & tumor[4]) and not np.any(tumor[4] & tumor[5])
    tumor[8] = _disk((N_PX, N_PX), (30, 60), 4)  # isolated group, far in z
    kept = _largest_linked_group(tumor, 3)
    expected = tumor.copy()
    expected[8] = False
    np.testing.assert_array_equal(kept, expected)
    # without the in-plane tolerance the drifting tumour falls apart
    split = _largest_linked_group(tumor, 0)
    assert np.count_nonzero(split.any(axis=(1, 2))) == 1


def test_segment_drops_distant_group_keeps_drifting_tumour_and_extends_tip():
    nz = 11
    tip = _disk((N_PX, N_PX), (47.5, 36.0), 3)  # 29 px on slice 2, inside slice 3's blob
    isolated = _disk((N_PX, N_PX), (30.0, 60.0), 4)  # 49 px on slice 9
    blobs = {2: [tip], 3: [_drift_blob(3)], 4: [_drift_blob(4)], 5: [_drift_blob(5)], 9: [isolated]}
    # slice 2 holds too little tumour for its own mode: detection calls it normal
    img, brain, det = _synthetic_case(blobs, {3, 4, 5, 9}, nz)
    res = segment_tumor(img, brain, det, modality="t2")
    sel = res.selection.tolist()
    assert sel[3:6] == ["reference"] * 3
    for z in (3, 4, 5):
        np.testing.assert_array_equal(res.tumor_mask[z], _drift_blob(z))
    assert sel[9] == "dropped-3d"
    assert not res.tumor_mask[9].any() and np.isnan(res.tumor_center_gray[9])
    assert sel[2] == "extended-3d"
    np.testing.assert_array_equal(res.tumor_mask[2], tip)
    assert abs(res.tumor_center_gray[2] - TUMOUR) < 10
    # the slice beyond the other end has no tip
    assert sel[6] == "" and not res.tumor_mask[6].any()
    expected_rows = [0, 0, tip.sum(), *(_drift_blob(z).sum() for z in (3, 4, 5)), 0, 0, 0, 0, 0]
    assert res.tumor_pixels.tolist() == expected_rows
    # without the 3-D rule the isolated group stays and no tip is added
    literal = segment_tumor(img, brain, det, modality="t2", keep_largest_3d_component=False)
    assert literal.tumor_mask[9].any() and not literal.tumor_mask[2].any()


def test_tips_are_decided_by_partial_volume_not_by_the_nearest_cluster():
    # a tumour on slices 3-5 (pure tumour disks in white matter); on slice 2 the
    # lower cap of a sphere (radius R, centre d mm above slice 2's centre plane)
    # fills part of the 2 mm slab: each pixel's gray is the white-matter /
    # tumour mixture by the share of the slab's thickness inside the sphere.
    # The pixel centre lies inside the sphere on the centre plane iff that share
    # exceeds 1/2, which is the truth the partial-volume rule must recover; most
    # of those pixels are nearer the grey-matter centre than the tumour's, so
    # the nearest-cluster rule loses the tip.
    nz, centre, radius_px = 8, (47.5, 36.0), 7
    body = _disk((N_PX, N_PX), centre, radius_px)
    img, brain, det = _synthetic_case({3: [body], 4: [body], 5: [body]}, {3, 4, 5}, nz)
    big_r, d_mm = 7.5, 6.8
    yy, xx = np.indices((N_PX, N_PX))
    rho2 = (yy - centre[0]) ** 2 + (xx - centre[1]) ** 2
    lowest = d_mm - np.sqrt(np.clip(big_r**2 - rho2, 0.0, None))  # sphere's bottom, mm
    share = np.where(rho2 < big_r**2, np.clip((1.0 - lowest) / 2.0, 0.0, 1.0), 0.0)
    img[2] = np.floor(WM + (TUMOUR - WM) * share + 0.5).astype(np.uint8)
    img[2][~brain[2]] = 0
    truth = rho2 < big_r**2 - d_mm**2  # inside the sphere on the centre plane
    assert truth.sum() >= 25
    ambiguous = np.abs(share - 0.5) < 0.01  # within gray-level rounding of 1/2
    gray2 = img[2].astype(np.float64)
    nearest_gm = truth & (np.abs(gray2 - GM) < np.abs(gray2 - TUMOUR))
    assert nearest_gm.sum() > truth.sum() // 2  # what the nearest-cluster rule gets wrong
    # beyond slice 5, inside its footprint: a CSF pocket (sulcus) with a
    # one-pixel grey matter / CSF partial-volume ring whose gray (175) is that
    # of a mostly-tumour pixel; it is no tip
    r_px = np.sqrt(rho2)
    img[6][r_px <= 4.2] = (GM + CSF) // 2
    img[6][r_px <= 3.0] = CSF
    assert np.count_nonzero((r_px > 3.0) & (r_px <= 4.2)) >= 20
    before = img.copy()

    res = segment_tumor(img, brain, det, modality="t2")

    np.testing.assert_array_equal(img, before)  # input untouched
    assert res.selection[2] == "extended-3d"
    tip = res.tumor_mask[2]
    assert tip[truth & ~ambiguous].all()
    assert not tip[~truth & ~ambiguous].any()
    assert abs(res.tumor_center_gray[2] - TUMOUR) < 10
    assert res.selection[6] == "" and not res.tumor_mask[6].any()
    np.testing.assert_array_equal(res.tumor_mask[3:6], np.stack([body] * 3))


def test_tip_partial_volume_is_judged_against_the_tip_slices_own_surround():
    # on the end slice the tumour abuts a CSF pool (its surround there is CSF, brighter
    # than the tumour); the tip on the next slice sits in white matter. A tip pixel
    # mixes the tumour with what lies around it on the tip slice, so the white matter
    # is its surround: the whole tip is found, nothing else
    nz, centre = 6, (47.5, 36.0)
    end_mask = _disk((N_PX, N_PX), centre, 7)
    img, brain, det = _synthetic_case({2: [end_mask], 3: [end_mask]}, {2, 3}, nz)
    pool = _disk((N_PX, N_PX), centre, 12) & ~end_mask
    img[2][pool] = CSF
    tip_truth = _disk((N_PX, N_PX), centre, 5)
    img[1][tip_truth] = TUMOUR
    res = segment_tumor(img, brain, det, modality="t2")
    np.testing.assert_array_equal(res.tumor_mask[2], end_mask)
    assert res.selection[1] == "extended-3d"
    np.testing.assert_array_equal(res.tumor_mask[1], tip_truth)


def _pixel_fractions(shape, centre, radius, sub=20) -> np.ndarray:
    """Fraction of each pixel (unit square around its centre) inside a disk."""
    offsets = (np.arange(sub) + 0.5) / sub - 0.5
    yy, xx = np.indices(shape, dtype=np.float64)
    frac = np.zeros(shape)
    for oy in offsets:
        for ox in offsets:
            frac += np.hypot(yy + oy - centre[0], xx + ox - centre[1]) < radius
    return frac / sub**2


@pytest.mark.parametrize(("tumour_gray", "surround_gray"), [(200, 80), (60, 150)])
def test_refine_boundary_decides_boundary_pixels_by_tumour_fraction(tumour_gray, surround_gray):
    shape = (64, 64)
    frac = _pixel_fractions(shape, (31.3, 32.6), 11.2)
    img = np.floor(surround_gray + (tumour_gray - surround_gray) * frac + 0.5).astype(np.uint8)
    brain = np.ones(shape, dtype=bool)
    # what FCM gives: the boundary pixels mixing tumour and tissue are labelled
    # with the cluster in between, only the mostly-tumour pixels remain
    mask = frac > 0.9
    partial = (frac > 0.5) & ~mask
    assert partial.sum() >= 15
    ambiguous = np.abs(frac - 0.5) < 0.01  # within gray-level rounding of 1/2
    img_before, mask_before = img.copy(), mask.copy()
    out = _refine_boundary(mask, img, brain, float(tumour_gray))
    assert out[(frac > 0.5) & ~ambiguous].all()
    assert not out[(frac < 0.5) & ~ambiguous].any()
    np.testing.assert_array_equal(img, img_before)
    np.testing.assert_array_equal(mask, mask_before)


# =========================================================================== interpolate: taper


def test_taper_caps_only_next_to_empty_neighbours():
    shape = (40, 40)
    c = (19.5, 19.5)
    masks = np.zeros((6,) + shape, dtype=bool)
    masks[0] = _disk(shape, c, 6)  # first slice of the stack: no cap before it
    masks[1] = _disk(shape, c, 8)  # then empty slices 2 and 3
    masks[4] = _disk(shape, (18, 21), 7)
    masks[5] = _disk(shape, c, 5)  # last slice of the stack
    m = 4
    step = m + 1
    taper = interpolate_stack(masks, slices_between=m, end_caps="taper")
    none = interpolate_stack(masks, slices_between=m, end_caps="none")
    n_fine = (len(masks) - 1) * step + 1
    assert taper.mask.shape == none.mask.shape == (n_fine,) + shape  # nothing beyond the ends
    np.testing.assert_array_equal(taper.mask[::step], masks)

    # "none" is the paper's stack: pairs interpolated, every other gap empty
    for k in range(len(masks) - 1):
        for j in range(1, step):
            if masks[k].any() and masks[k + 1].any():
                want = interpolate_pair(masks[k], masks[k + 1], j / step)
            else:
                want = np.zeros(shape, dtype=bool)
            np.testing.assert_array_equal(none.mask[k * step + j], want)
    # taper changes only the two gaps next to the empty slices
    changed = np.flatnonzero((taper.mask != none.mask).any(axis=(1, 2)))
    assert set(changed) == set(range(6, 10)) | set(range(16, 20))
    assert not taper.mask[11:15].any()  # between two empty slices

    for end, cap in ((masks[1], [6, 7, 8, 9]), (masks[4], [19, 18, 17, 16])):
        areas = [int(end.sum())] + [int(taper.mask[j].sum()) for j in cap]
        assert all(a > b > 0 for a, b in zip(areas, areas[1:], strict=False)), areas
        for outer, inner in zip(
            [end] + [taper.mask[j] for j in cap], [taper.mask[j] for j in cap], strict=False
        ):
            assert not np.any(inner & ~outer)  # nested: the cap shrinks inside the end mask
        assert taper.interpolated[cap].all()
    assert not none.interpolated[6:10].any()


def _sphere_masks(radius_mm: float, step_mm: float, phase_mm: float, n_px: int = 32):
    """Slice masks (1 mm pixels) of a sphere at the origin, planes at phase + k step."""
    coords = np.arange(n_px) - (n_px - 1) / 2.0
    yy, xx = np.meshgrid(coords, coords, indexing="ij")
    rho2 = yy**2 + xx**2
    k_max = int(np.ceil((radius_mm + step_mm) / step_mm)) + 1
    zs = phase_mm + step_mm * np.arange(-k_max, k_max + 1)
    masks = np.stack([rho2 < radius_mm**2 - z**2 for z in zs])
    assert not masks[0].any() and not masks[-1].any()  # empty slices beyond both ends
    return masks


def test_taper_removes_the_flat_cap_bias_on_a_sphere():
    radius, step, m = 10.0, 5.0, 4
    affine = np.diag([1.0, 1.0, step, 1.0])
    v_true = 4.0 / 3.0 * np.pi * radius**3
    phases = np.random.default_rng(7).uniform(0.0, step, 8)
    errors = {"none": [], "taper": []}
    for phase in phases:
        masks = _sphere_masks(radius, step, phase)
        for caps in errors:
            stack = interpolate_stack(masks, slices_between=m, end_caps=caps)
            mesh = extract_surface(stack.mask, stack.fine_affine(affine))
            errors[caps].append((mesh_volume_mm3(mesh) - v_true) / v_true)
    mean = {k: float(np.mean(v)) for k, v in errors.items()}
    # flat caps miss two caps of expected volume ~ pi R h^2 / 3 each (-11 %)
    assert mean["none"] < -0.05
    assert abs(mean["taper"]) < abs(mean["none"])
    # and the taper does not overshoot: shape-based interpolation between
    # concentric disks follows chords of the sphere (inside it) and the cone
    # over the end slice holds on average a little less than the true cap
    # (pi h (R h - h^2 / 3) / 3 against pi (R h^2 - h^3 / 4) / 3)
    assert mean["none"] < mean["taper"] < 0.0


def test_invalid_end_caps_is_rejected():
    masks = np.zeros((3, 8, 8), dtype=bool)
    masks[1, 2:6, 2:6] = True
    with pytest.raises(InputError, match="end_caps"):
        interpolate_stack(masks, slices_between=1, end_caps="round")
