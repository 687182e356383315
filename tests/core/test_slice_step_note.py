"""The header's slice step checked against the head's own shape (tumor3d.imaging.preprocess).

Images exported without their voxel size are often written with a nominal 1 mm: the 45
clinical LGG heads of the shared data are, and every volume in mL was silently wrong by
the true step's factor. The head's outline then moves several "steps" per slice; with the
true step it moves at most about one.
"""

from __future__ import annotations

import numpy as np
import pytest

from tumor3d.imaging.preprocess import (
    MAX_OUTLINE_SHIFT_STEPS,
    brain_mask_figures,
    brain_mask_notes,
    outline_shift_mm,
    preprocess_volume,
)
from tumor3d.phantom import make_phantom_patient


@pytest.fixture(scope="module")
def phantom():
    return make_phantom_patient(11, n_slices=24, matrix_size=(128, 128)).scan


def _size_notes(image, spacing_mm):
    pre = preprocess_volume(image, spacing_mm=spacing_mm)
    figures = brain_mask_figures(pre.brain_mask, spacing_mm, pre.brain_extraction, pre.original_u8)
    return figures, brain_mask_notes(figures)[1]


def test_a_sphere_moves_its_outline_by_its_radius_steps():
    """Independent: a ball of radius 40 mm cut every 4 mm; the outlines' shift between
    neighbouring slices is the difference of their radii (the median over the slices
    whose section is at least a quarter of the largest)."""
    zz, yy, xx = np.mgrid[-40:41:4, -60:60, -60:60].astype(float)
    ball = ((zz**2 + yy**2 + xx**2) < 40.0**2).astype(np.uint8) * 200
    radii = np.sqrt(np.maximum(40.0**2 - np.arange(-40, 41, 4.0) ** 2, 0))
    big = np.pi * radii**2 >= 0.25 * np.pi * 40.0**2
    steps = [abs(radii[k + 1] - radii[k]) for k in range(len(radii) - 1) if big[k] and big[k + 1]]
    assert outline_shift_mm(ball, (4.0, 1.0, 1.0)) == pytest.approx(np.median(steps), abs=0.6)


def test_the_true_step_gives_no_note_and_a_nominal_one_doubts_every_volume(phantom):
    step, dy, dx = phantom.spacing_zyx_mm
    assert step == 5.0
    figures, size = _size_notes(phantom.image, (step, dy, dx))
    assert size == []
    assert figures["outline_shift_mm"] < MAX_OUTLINE_SHIFT_STEPS * step
    # the same slices with a nominal 1 mm step, as an export without voxel size writes them
    figures, size = _size_notes(phantom.image, (1.0, dy, dx))
    assert len(size) == 1 and "slice step in the header (1 mm)" in size[0]
    assert figures["outline_shift_mm"] > MAX_OUTLINE_SHIFT_STEPS * 1.0


def test_a_nominal_step_makes_the_run_check():
    """Through the Python API, a phantom of 1 mm pixels and 5 mm slices written as an
    export without voxel size writes it (1 x 1 x 1 mm): the run asks for a check and
    names the step; its true voxel size gives no such note."""
    import tumor3d

    scan = make_phantom_patient(12, n_slices=24, matrix_size=(200, 200), pixel_spacing_mm=1.0).scan
    image = scan.source_grid.to_source(scan.image)
    true = tumor3d.reconstruct(image, affine=scan.source_grid.affine, modality="t2")
    assert not [n for n in true.notes if "slice step in the header" in n]
    nominal = np.diag([-1.0, -1.0, 1.0, 1.0])
    r = tumor3d.reconstruct(image, affine=nominal, modality="t2")
    assert r.status == "check"
    assert any("slice step in the header (1 mm)" in reason for reason in r.review_reasons)


def test_a_masked_brain_is_measured_by_its_support_not_its_dark_tissue():
    """A skull-stripped brain (zero all around) whose dark tissue reaches its edge by a
    different amount on each slice (a dark wedge of 90 degrees on every other slice, below
    half the Otsu level, as the algoseg T2's white matter was): the outline is the brain's
    support, so the shift is the ball's own radius steps (independent: as the sphere test
    above), not the wedge's come and go (2.6 mm by the threshold)."""
    zz, yy, xx = np.mgrid[-40:41:4, -60:60, -60:60].astype(float)
    ball = (zz**2 + yy**2 + xx**2) < 40.0**2
    width = np.where(np.arange(len(zz))[:, None, None] % 2 == 0, 90.0, 0.0)
    wedge = ball & (np.abs(np.degrees(np.arctan2(yy, xx))) < width / 2)
    tissue = np.random.default_rng(0).integers(20, 220, size=ball.shape)
    brain = np.where(wedge, 10, np.where(ball, tissue, 0)).astype(np.uint8)
    radii = np.sqrt(np.maximum(40.0**2 - np.arange(-40, 41, 4.0) ** 2, 0))
    big = np.pi * radii**2 >= 0.25 * np.pi * 40.0**2
    steps = [abs(radii[k + 1] - radii[k]) for k in range(len(radii) - 1) if big[k] and big[k + 1]]
    assert outline_shift_mm(brain, (4.0, 1.0, 1.0)) == pytest.approx(np.median(steps), abs=0.3)


def test_a_slab_of_one_end_of_the_head_gets_no_verdict():
    """A stack from the head's widest section up holds only its steep part (the top 40 mm
    of a 1 mm brain moved 1.1 steps, a coronal 3 mm head's first 8 slices 2.2: false
    alarms): with the largest section on an end slice nothing is measured. A ball of
    radius 40 mm cut every 4 mm, widest at z = 0 (index 10)."""
    zz, yy, xx = np.mgrid[-40:41:4, -60:60, -60:60].astype(float)
    ball = ((zz**2 + yy**2 + xx**2) < 40.0**2).astype(np.uint8) * 200
    spacing = (4.0, 1.0, 1.0)
    assert outline_shift_mm(ball, spacing) is not None
    assert outline_shift_mm(ball[10:], spacing) is None  # the upper half
    assert outline_shift_mm(ball[:11], spacing) is None  # the lower half
    assert outline_shift_mm(ball[9:], spacing) is not None  # through the widest: measured


def test_a_slice_step_too_large_makes_the_brain_taller_than_any_head(phantom):
    """A user audit: 31 slices 5 mm apart written as 10 mm (or 50 mm) doubled (tenfold)
    every volume with status ok; the outline's shift only sees a step too small. The
    brain mask's height along the slices (its slices times the step) is the check: the
    phantom's 24 slices at 5 mm make no note; at 12 mm the brain is taller than any head."""
    from tumor3d.imaging.preprocess import MAX_BRAIN_HEIGHT_MM

    step, dy, dx = phantom.spacing_zyx_mm
    figures, size = _size_notes(phantom.image, (step, dy, dx))
    n = figures["brain_slices"]
    assert size == [] and n * step <= MAX_BRAIN_HEIGHT_MM
    too_large = MAX_BRAIN_HEIGHT_MM / n * 1.05  # the brain 5 % taller than the limit
    figures, size = _size_notes(phantom.image, (too_large, dy, dx))
    assert figures["brain_slices"] == n
    (note,) = size
    assert note.startswith(f"brain mask on {n} slices of {too_large:g} mm:")
    assert "slice step in the header is likely too large" in note


def test_a_slice_step_too_large_makes_the_run_check():
    import tumor3d

    scan = make_phantom_patient(12, n_slices=24, matrix_size=(200, 200), pixel_spacing_mm=1.0).scan
    image = scan.source_grid.to_source(scan.image)
    wrong = scan.source_grid.affine.copy()
    wrong[:3, 2] *= 4.0  # 20 mm slices written for 5 mm
    r = tumor3d.reconstruct(image, affine=wrong, modality="t2")
    assert r.status == "check"
    assert any("likely too large" in reason for reason in r.review_reasons)
