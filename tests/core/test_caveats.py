"""Caveats (tumor3d.segmentation.caveats): said exactly when their situation holds.

Independent expectations: the plane's signed distance against the textbook
point-to-line distance, the end-slice and midline situations built on
purpose (a disc straddling the plane, the same disc 20 mm away, on one slice
only), and the robust segmentation saying the midline caveat where the peer,
which has no symmetry rule, does not.
"""

from __future__ import annotations

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.segmentation.caveats import (
    midline_caveat,
    scalp_caveat,
    scan_end_caveat,
    segmentation_caveats,
    symmetric_caveat,
)
from tumor3d.segmentation.detect import SliceDetection
from tumor3d.segmentation.lesion import (
    SYMMETRY_TOLERANCE_MM,
    LesionResult,
    MirrorPlane,
    NormalModel,
)
from tumor3d.segmentation.review import review_status, run_notes
from tumor3d.segmentation.segment import segment_tumor

SHAPE = (6, 96, 96)
PIXEL_MM = (0.8, 0.8)
PIXEL_AREA_MM2 = PIXEL_MM[0] * PIXEL_MM[1]
SPACING = (5.0, *PIXEL_MM)
#: the vertical line through column 48 (the grid's middle) and a point of it, (y, x) in mm
MID_PLANE = MirrorPlane(2, 0.0, 48 * PIXEL_MM[1])
CENTRE = (48 * PIXEL_MM[0], 48 * PIXEL_MM[1])


def _disc(centre_yx_mm, radius_mm, slices, shape=SHAPE, pixel_mm=PIXEL_MM):
    y, x = np.indices(shape[1:], dtype=float)
    d = np.hypot(y * pixel_mm[0] - centre_yx_mm[0], x * pixel_mm[1] - centre_yx_mm[1])
    m = np.zeros(shape, bool)
    m[list(slices)] = d <= radius_mm
    return m


@pytest.mark.parametrize("yaw_deg", [0.0, 12.5, -30.0])
@pytest.mark.parametrize("axis", [1, 2])
def test_signed_distance_is_the_point_to_line_distance(axis, yaw_deg):
    plane = MirrorPlane(axis, yaw_deg, 31.7)
    d = plane.signed_distance_mm((40, 50), (0.7, 1.1))
    # the line n . p = offset holds the point offset * n and runs along the tangent t
    n = plane.normal()
    t = np.array([-n[1], n[0]])
    a = 31.7 * n
    rng = np.random.default_rng(0)
    for row, col in zip(rng.integers(0, 40, 25), rng.integers(0, 50, 25), strict=True):
        p = np.array([row * 0.7, col * 1.1])
        # |cross(t, p - a)| with the sign of the side the normal points to
        dist = abs(t[0] * (p - a)[1] - t[1] * (p - a)[0])
        assert abs(d[row, col]) == pytest.approx(dist, abs=1e-9)
        assert np.sign(d[row, col]) == np.sign(np.dot(p - a, n))


def test_scan_end_caveat_names_the_end_slices_the_tumour_reaches():
    m = np.zeros((5, 8, 8), bool)
    assert scan_end_caveat(m) is None
    m[2, 3:5, 3:5] = True
    assert scan_end_caveat(m) is None  # inside the scanned range
    m[0, 3, 3] = True
    first = scan_end_caveat(m)
    assert "first slice of the scan (slice 0, 0-based)" in first and "last" not in first
    assert "underestimate" in first
    m[0] = False
    m[4, 3, 3] = True
    last = scan_end_caveat(m)
    assert "last slice of the scan (slice 4, 0-based)" in last and "first" not in last
    m[0, 3, 3] = True
    assert "first and last slices of the scan (slices 0 and 4, 0-based)" in scan_end_caveat(m)
    one = np.ones((1, 4, 4), bool)  # a single slice is its own first and last
    assert "first slice of the scan (slice 0, 0-based)" in scan_end_caveat(one)


def test_midline_caveat_only_for_a_significant_cross_section_at_the_plane():
    plane = MID_PLANE
    centre = CENTRE
    kw = {"min_region_mm2": 50 * PIXEL_AREA_MM2, "min_slices": 2}
    straddling = _disc(centre, 8.0, slices=(1, 2, 3))
    note = midline_caveat(straddling, plane, SPACING, **kw)
    assert note is not None and "slices 1-3" in note
    # the band is +-2.5 mm: about 6 columns x 20 rows = 120 pixels a slice
    band = np.abs(plane.signed_distance_mm(SHAPE[1:], PIXEL_MM)) <= SYMMETRY_TOLERANCE_MM / 2
    assert 50 <= np.count_nonzero(straddling[1] & band) <= 200
    # the same disc 20 mm to the side: no voxel within the band
    lateral = _disc((centre[0], centre[1] + 20.0), 8.0, slices=(1, 2, 3))
    assert midline_caveat(lateral, plane, SPACING, **kw) is None
    # on one slice only: not significant (min_slices 2), significant with min_slices 1
    single = _disc(centre, 8.0, slices=(2,))
    assert midline_caveat(single, plane, SPACING, **kw) is None
    assert midline_caveat(single, plane, SPACING, min_region_mm2=50 * PIXEL_AREA_MM2, min_slices=1)
    # a thin contact (less band area than min_region_mm2) is no cross-section
    strict = {"min_region_mm2": 500 * PIXEL_AREA_MM2, "min_slices": 2}
    assert midline_caveat(straddling, plane, SPACING, **strict) is None


@pytest.mark.parametrize("pixel_mm", [0.5, 1.0, 2.0])
def test_midline_caveat_area_is_in_mm2_down_to_1_mm_pixels_then_a_pixel_count(pixel_mm):
    # a rectangle straddling the plane, 4 mm wide (all of it within the +-2.5 mm band) and
    # 10, 16 or 28 mm tall: 40, 64 or 112 mm2 of band a slice, against a rule of 50 mm2.
    # At 0.5 and 1 mm pixels the rule is the area (at 0.5 mm 160 and 256 pixels: a count
    # in pixels would say both); at 2 mm pixels it is the 50 pixels it has at 1 mm
    # (200 mm2): 10, 16 and 28 pixels say nothing
    n = int(round(64 / pixel_mm))
    shape = (4, n, n)
    mid = n // 2
    plane = MirrorPlane(2, 0.0, mid * pixel_mm)
    half_w = int(round(2.0 / pixel_mm))
    rule = {"min_region_mm2": 50.0, "min_slices": 2}
    for tall_mm, said in ((10.0, False), (16.0, True), (28.0, True)):
        said = said and pixel_mm <= 1.0
        m = np.zeros(shape, bool)
        m[1:3, 4 : 4 + int(round(tall_mm / pixel_mm)), mid - half_w : mid + half_w] = True
        area_mm2 = m[1].sum() * pixel_mm**2
        assert area_mm2 == pytest.approx(4.0 * tall_mm)
        got = midline_caveat(m, plane, (5.0, pixel_mm, pixel_mm), **rule)
        assert (got is not None) == said, (pixel_mm, tall_mm)
    if pixel_mm > 1.0:  # 26 x 2 = 52 pixels (208 mm2): said
        m = np.zeros(shape, bool)
        m[1:3, 4:30, mid - half_w : mid + half_w] = True
        assert midline_caveat(m, plane, (5.0, pixel_mm, pixel_mm), **rule) is not None


def test_midline_caveat_names_each_run_of_slices():
    plane = MID_PLANE
    centre = CENTRE
    kw = {"min_region_mm2": 50 * PIXEL_AREA_MM2, "min_slices": 2}
    m = np.zeros((14, 96, 96), bool)
    m[[1, 2, 3, 9, 10]] = _disc(centre, 8.0, slices=(0,))[0]
    note = midline_caveat(m, plane, SPACING, **kw)
    assert "on slices 1-3, 9-10 (0-based" in note
    # big cross-sections on slices 1 and 3 only are no run of two consecutive slices
    m[[2, 9, 10]] = False
    assert midline_caveat(m, plane, SPACING, **kw) is None
    one = midline_caveat(m, plane, SPACING, min_region_mm2=50 * PIXEL_AREA_MM2, min_slices=1)
    assert "on slices 1, 3 (0-based" in one
    m[3] = False
    assert "on slice 1 (0-based" in midline_caveat(
        m, plane, SPACING, min_region_mm2=50 * PIXEL_AREA_MM2, min_slices=1
    )


@pytest.mark.parametrize("pixel_mm", [(0.8, 0.8), (0.5, 1.25), (1.25, 0.5)])
def test_midline_band_is_half_the_symmetry_tolerance_in_mm(pixel_mm):
    # a strip of tissue parallel to the plane at 2.0 mm is in the band, at 3.0 mm it is not
    # (the band is +-2.5 mm, whatever the pixels' shape)
    shape = (4, 120, 200)
    plane = MirrorPlane(2, 0.0, 60.0)  # the vertical line x = 60 mm
    y, x = np.indices(shape[1:], dtype=float)
    x_mm = x * pixel_mm[1]
    kw = {"min_region_mm2": 20 * PIXEL_AREA_MM2, "min_slices": 2}
    for gap_mm, said in ((2.0, True), (3.0, False)):
        strip = (x_mm >= 60.0 + gap_mm) & (x_mm <= 60.0 + gap_mm + 10.0)
        m = np.zeros(shape, bool)
        m[1:3] = strip & (y * pixel_mm[0] < 40.0)
        assert m[1].sum() >= 20
        got = midline_caveat(m, plane, (5.0, *pixel_mm), **kw)
        assert (got is not None) == said, (gap_mm, pixel_mm)


def test_without_spacing_the_voxels_are_1_mm():
    plane = MirrorPlane(2, 0.0, 48.0)
    m = np.zeros(SHAPE, bool)
    m[1:4, 20:70, 51:54] = True  # 3 to 5 mm from the plane at 1 mm pixels: out of the band
    assert segmentation_caveats(m, plane=plane) == ()
    m[1:4, 20:70, 49:52] = True  # 1 to 3 mm at 1 mm pixels: 2 columns in the band
    assert segmentation_caveats(m, plane=plane) == segmentation_caveats(
        m, plane=plane, spacing_mm=(1.0, 1.0, 1.0)
    )
    assert len(segmentation_caveats(m, plane=plane)) == 1
    # at 0.5 mm pixels the same columns lie 0.5-2.5 mm away: all in the band, said as well
    assert len(segmentation_caveats(m, plane=MirrorPlane(2, 0.0, 24.0),
                                    spacing_mm=(1.0, 0.5, 0.5))) == 1


def test_midline_caveat_follows_a_turned_plane():
    # a plane turned by 25 degrees; a disc on it far from the rows' centre lies well off
    # the unturned plane through the same offset
    plane = MirrorPlane(2, 25.0, 30.0)
    n = plane.normal()
    t = np.array([-n[1], n[0]])
    on_plane = 30.0 * n - 45.0 * t  # a point of the line, (y, x) in mm
    assert 10 < on_plane[0] < 70 and 10 < on_plane[1] < 70
    disc = _disc(tuple(on_plane), 6.0, slices=(0, 1, 2, 3, 4, 5))
    kw = {"min_region_mm2": 30 * PIXEL_AREA_MM2, "min_slices": 2}
    assert midline_caveat(disc, plane, SPACING, **kw) is not None
    unturned = MirrorPlane(2, 0.0, 30.0)
    assert midline_caveat(disc, unturned, SPACING, **kw) is None


def test_caveats_survive_the_notes_separator():
    # the run's notes are joined with "; " in metrics.parquet and split on it again
    plane = MID_PLANE
    m = _disc(CENTRE, 8.0, slices=(0, 1, 2, 3, 4, 5))
    notes = segmentation_caveats(m, plane=plane, spacing_mm=SPACING)
    assert len(notes) == 2
    assert "; ".join(notes).split("; ") == list(notes)


def test_segmentation_caveats_skips_the_midline_without_a_plane():
    plane = MID_PLANE
    m = _disc(CENTRE, 8.0, slices=(0, 1, 2))
    both = segmentation_caveats(m, plane=plane, spacing_mm=SPACING)
    assert len(both) == 2 and "first slice" in both[0] and "midline" in both[1]
    assert segmentation_caveats(m, spacing_mm=SPACING) == both[:1]
    assert segmentation_caveats(np.zeros(SHAPE, bool), plane=plane, spacing_mm=SPACING) == ()
    with pytest.raises(InputError, match="shape"):
        segmentation_caveats(np.zeros((4, 4), bool))


def test_the_midline_caveat_is_shown_and_the_others_doubt_the_volume():
    """The status rule reads the caveats as the functions above write them: the midline
    caveat is a note (out of fold it named bad and good volumes alike, INFORMING_CAVEATS),
    the scan-end caveat beside it a doubt that makes the status check."""
    m = _disc(CENTRE, 8.0, slices=(0, 1, 2))
    end, midline = segmentation_caveats(m, plane=MID_PLANE, spacing_mm=SPACING)
    notes, doubts = run_notes(tumour_found=True, caveats=[end, midline])
    assert notes == [end, midline] and doubts == [end]
    assert review_status(doubts).status == "check"
    alone = segmentation_caveats(_disc(CENTRE, 8.0, slices=(1, 2, 3)), plane=MID_PLANE,
                                 spacing_mm=SPACING)  # fmt: skip
    notes, doubts = run_notes(tumour_found=True, caveats=alone)
    assert len(alone) == 1 and notes == list(alone) and doubts == []
    assert review_status(doubts).status == "ok"


def _detection_with_lesion(mask, plane, midline=False):
    nz = mask.shape[0]
    model = NormalModel(100.0, 10.0, 120.0, float("inf"))
    lesion = LesionResult(mask, model, 200.0, 150.0, 1, plane, midline)
    return SliceDetection(
        n_modes=np.full(nz, 4),
        abnormal=mask.any(axis=(1, 2)),
        peaks_gray=tuple(np.array([100.0]) for _ in range(nz)),
        brain_pixels=np.full(nz, 5000),
        lesion=lesion,
    )


def test_robust_segmentation_says_the_midline_caveat_and_the_peer_does_not():
    plane = MID_PLANE
    brain = np.zeros(SHAPE, bool)
    brain[:, 8:88, 8:88] = True
    img = np.where(brain, 100, 0).astype(np.uint8)
    img[:, 8:30, 8:88] = 60  # four gray levels, so that the peer's multi-Otsu has 4 classes
    img[:, 66:88, 8:88] = 140
    straddling = _disc(CENTRE, 8.0, slices=(1, 2, 3))
    img[straddling] = 220
    det = _detection_with_lesion(straddling, plane)
    robust = segment_tumor(img, brain, det, modality="flair", method="robust", spacing_mm=SPACING)
    assert robust.tumor_mask.any()
    assert any("reaches the brain's midline" in c for c in robust.caveats)
    assert not any("slice of the scan" in c for c in robust.caveats)
    # the same lesion 20 mm to the side: nothing to say
    lateral = _disc((CENTRE[0], CENTRE[1] + 20.0), 8.0, slices=(1, 2, 3))
    det = _detection_with_lesion(lateral, plane)
    res = segment_tumor(img, brain, det, modality="flair", method="robust", spacing_mm=SPACING)
    assert res.tumor_mask.any() and res.caveats == ()
    # the significance rule is the configuration's (detect.lesion), not a constant: with
    # min_region_mm2 above the band's ~110 pixels a slice a lesion reaching the midline
    # says nothing (one 5 mm off the plane: a quarter of it is its own mirror image, so
    # the midline caveat is the one that applies)
    near = _disc((CENTRE[0], CENTRE[1] + 5.0), 8.0, slices=(1, 2, 3))
    img[near] = 220
    det = _detection_with_lesion(near, plane)
    res = segment_tumor(img, brain, det, modality="flair", method="robust", spacing_mm=SPACING)
    assert res.tumor_mask.any() and any("other hemisphere" in c for c in res.caveats)
    strict = segment_tumor(img, brain, det, modality="flair", method="robust",
                           spacing_mm=SPACING, lesion={"min_region_mm2": 500 * PIXEL_AREA_MM2})
    assert strict.tumor_mask.any() and strict.caveats == ()
    # the peer has no symmetry rule: it says no midline caveat, even on the midline lesion
    det = _detection_with_lesion(straddling, plane)
    peer = segment_tumor(img, brain, det, modality="flair", method="multiotsu", spacing_mm=SPACING)
    assert (peer.tumor_mask & straddling).sum() > 0.9 * straddling.sum()
    assert not any("midline" in c for c in peer.caveats)


def _lens_share(offset_mm: float, radius_mm: float) -> float:
    """Share of a disc's area that its mirror image covers (centre ``offset_mm`` off)."""
    d, r = 2.0 * offset_mm, radius_mm
    lens = 2 * r * r * np.arccos(d / (2 * r)) - 0.5 * d * np.sqrt(4 * r * r - d * d)
    return lens / (np.pi * r * r)


@pytest.mark.parametrize("yaw_deg", [0.0, 20.0])
def test_symmetric_caveat_says_how_much_of_the_tumour_is_its_own_mirror_image(yaw_deg):
    # independent expectation: the lens of a disc and its mirror image, in closed form
    n = MirrorPlane(2, yaw_deg, 0.0).normal()
    # the plane through the grid's centre
    plane = MirrorPlane(2, yaw_deg, float(n[0] * CENTRE[0] + n[1] * CENTRE[1]))
    for offset_mm in (0.0, 1.5, 2.5, 4.0, 6.0):
        c = (CENTRE[0] + offset_mm * n[0], CENTRE[1] + offset_mm * n[1])
        disc = _disc(c, 8.0, slices=(1, 2, 3))
        note = symmetric_caveat(disc, plane, SPACING)
        said = float(note.split("is ")[1].split(" %")[0]) / 100.0
        assert said == pytest.approx(_lens_share(offset_mm, 8.0), abs=0.04)
    assert symmetric_caveat(np.zeros(SHAPE, bool), plane, SPACING) is None


def test_a_lesion_found_by_step_3f_says_so_in_place_of_the_midline_caveat():
    disc = _disc(CENTRE, 8.0, slices=(1, 2, 3))
    said = segmentation_caveats(disc, plane=MID_PLANE, spacing_mm=SPACING, midline_lesion=True)
    assert len(said) == 1 and "own mirror image" in said[0] and "brightness and depth" in said[0]
    # found otherwise (an asymmetric core, with its part across the plane): the midline
    # caveat, whatever its share of mirrored voxels
    said = segmentation_caveats(disc, plane=MID_PLANE, spacing_mm=SPACING)
    assert len(said) == 1 and "reaches the brain's midline" in said[0]
    # through segment_tumor: the detection's lesion carries the flag
    brain = np.zeros(SHAPE, bool)
    brain[:, 8:88, 8:88] = True
    img = np.where(brain, 100, 0).astype(np.uint8)
    img[disc] = 220
    det = _detection_with_lesion(disc, MID_PLANE, midline=True)
    res = segment_tumor(img, brain, det, modality="flair", method="robust", spacing_mm=SPACING)
    assert any("own mirror image" in c for c in res.caveats)
    assert not any("reaches the brain's midline" in c for c in res.caveats)


def _air_left_of(column: int, shape=SHAPE) -> np.ndarray:
    air = np.zeros(shape, bool)
    air[:, :, :column] = True
    return air


@pytest.mark.parametrize("pixel_mm", [(0.8, 0.8), (0.5, 0.5), (1.0, 2.0)])
def test_scalp_caveat_is_said_within_5_mm_of_the_air_in_mm(pixel_mm):
    """The distance is in mm through the pixel spacing, not in pixels."""
    air = _air_left_of(4)
    spacing = (5.0, *pixel_mm)
    # a disc whose left edge lies 3 mm from the air (column 3 is the air's last), and
    # the same disc with its left edge 7 mm away: an independent in-mm construction
    for gap_mm, says in ((3.0, True), (7.0, False)):
        centre_x_mm = 3 * pixel_mm[1] + gap_mm + 6.0
        m = _disc((48 * pixel_mm[0], centre_x_mm), 6.0, slices=(2, 3), pixel_mm=pixel_mm)
        note = scalp_caveat(m, air, spacing)
        assert (note is not None) == says, (pixel_mm, gap_mm, note)
    assert "on slices 2-3 (0-based" in scalp_caveat(
        _disc((48 * pixel_mm[0], 3 * pixel_mm[1] + 9.0), 6.0, (2, 3), pixel_mm=pixel_mm),
        air, spacing,
    )  # fmt: skip


def test_scalp_caveat_names_the_slices_and_the_volume_near_the_air():
    air = _air_left_of(4)
    m = np.zeros(SHAPE, bool)
    m[1, 40:50, 4:10] = True  # 60 pixels touching the air: all within 5 mm (0.8 mm pixels)
    m[4, 40:50, 60:70] = True  # far from it
    note = scalp_caveat(m, air, SPACING)
    ml = 60 * SPACING[0] * PIXEL_AREA_MM2 / 1000.0
    assert note.startswith("tumour within 5 mm of the air outside the head on slice 1 (0-based;")
    assert f"{ml:.2f} mL of it" in note and "brain_extraction: head" in note
    with pytest.raises(InputError, match="differ in shape"):
        scalp_caveat(m, air[:, :, :10], SPACING)


def test_segmentation_says_the_scalp_caveat_only_with_the_air_of_a_raw_head():
    brain = np.zeros(SHAPE, bool)
    brain[:, 8:88, 8:88] = True
    img = np.where(brain, 100, 0).astype(np.uint8)
    img[:, 8:30, 8:88] = 60
    img[:, 66:88, 8:88] = 140
    lesion = _disc((48 * PIXEL_MM[0], 12 * PIXEL_MM[1]), 5.0, slices=(1, 2, 3))  # at the edge
    img[lesion] = 220
    det = _detection_with_lesion(lesion, None)
    air = _air_left_of(8)  # the air right outside the brain mask's left edge
    for method in ("robust", "multiotsu"):
        raw = segment_tumor(img, brain, det, modality="flair", method=method,
                            spacing_mm=SPACING, head_exterior=air)  # fmt: skip
        assert raw.tumor_mask.any()
        assert any("air outside the head" in c for c in raw.caveats), method
        stripped = segment_tumor(img, brain, det, modality="flair", method=method,
                                 spacing_mm=SPACING)  # fmt: skip
        assert not any("air outside the head" in c for c in stripped.caveats), method
