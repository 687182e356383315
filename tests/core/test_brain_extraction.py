"""Tests of tumor3d.imaging.brain_extraction on synthetic heads (no real data)."""

from __future__ import annotations

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.imaging.brain_extraction import extract_brain

BRAIN, SKULL, SCALP = 100, 15, 210
SEMI_AXES_MM = np.array([60.0, 75.0, 65.0])  # brain (z, y, x) semi-axes
SKULL_MM, SCALP_MM = 6.0, 6.0


def _dice(a: np.ndarray, b: np.ndarray) -> float:
    return 2.0 * np.count_nonzero(a & b) / (np.count_nonzero(a) + np.count_nonzero(b))


def _head(spacing, *, bridge=SCALP, seed=0):
    """Ellipsoidal brain in a dark skull shell in a bright scalp shell (+ noise).

    Returns the uint8 image, the true brain and the scalp masks. ``bridge``
    (an intensity, or None) adds a 4 mm bar of it through the skull joining
    brain and scalp: fat-bright (marrow) or brain-like (partial volume).
    """
    sz, sy, sx = spacing
    half = SEMI_AXES_MM + SKULL_MM + SCALP_MM + 10.0
    z = np.arange(-half[0], half[0] + 1e-9, sz)
    y = np.arange(-half[1], half[1] + 1e-9, sy)
    x = np.arange(-half[2], half[2] + 1e-9, sx)
    zz, yy, xx = np.meshgrid(z, y, x, indexing="ij")
    rho = np.sqrt(
        (zz / SEMI_AXES_MM[0]) ** 2 + (yy / SEMI_AXES_MM[1]) ** 2 + (xx / SEMI_AXES_MM[2]) ** 2
    )
    depth_out = (rho - 1.0) * SEMI_AXES_MM.min()  # approximate mm outside the brain
    brain = rho < 1.0
    skull = ~brain & (depth_out < SKULL_MM)
    scalp = ~brain & ~skull & (depth_out < SKULL_MM + SCALP_MM)
    image = np.zeros(brain.shape)
    image[brain], image[skull], image[scalp] = BRAIN, SKULL, SCALP
    if bridge is not None:
        bar = (np.abs(zz) < 2.0) & (np.abs(yy) < 2.0) & (xx > 0) & (brain | skull | scalp)
        image[bar & ~brain] = bridge
    rng = np.random.default_rng(seed)
    image = image + rng.normal(0.0, 4.0, image.shape) * (image > 0)
    return np.clip(np.rint(image), 0, 255).astype(np.uint8), brain, scalp


@pytest.mark.parametrize("spacing", [(1.5, 1.5, 1.5), (6.5, 0.8, 0.8), (5.0, 4.0, 4.0)])
def test_matches_true_brain_and_excludes_scalp(spacing):
    image, brain, scalp = _head(spacing)
    mask = extract_brain(image, spacing)
    assert _dice(mask, brain) >= 0.95
    assert np.count_nonzero(mask & scalp) <= 0.001 * np.count_nonzero(scalp)


@pytest.mark.parametrize("bridge", [SCALP, BRAIN])
def test_bridge_does_not_carry_scalp_in(bridge):
    spacing = (2.0, 1.0, 1.0)
    image, brain, scalp = _head(spacing, bridge=bridge)
    mask = extract_brain(image, spacing)
    assert not (mask & scalp).any()


def test_same_brain_volume_at_1mm_and_thick_slices():
    volumes = []
    for spacing in [(1.0, 1.0, 1.0), (6.0, 1.0, 1.0)]:
        image, _, _ = _head(spacing)
        volumes.append(np.count_nonzero(extract_brain(image, spacing)) * np.prod(spacing))
    true_ml = 4.0 / 3.0 * np.pi * np.prod(SEMI_AXES_MM)
    assert volumes[0] == pytest.approx(true_ml, rel=0.05)
    assert volumes[1] == pytest.approx(volumes[0], rel=0.05)


def test_does_not_modify_input():
    image, _, _ = _head((4.0, 2.0, 2.0))
    before = image.copy()
    extract_brain(image, (4.0, 2.0, 2.0))
    np.testing.assert_array_equal(image, before)


@pytest.mark.parametrize("value", [0, 77])
def test_constant_volume_gives_empty_mask(value):
    mask = extract_brain(np.full((5, 20, 20), value, dtype=np.uint8), (2.0, 2.0, 2.0))
    assert mask.shape == (5, 20, 20) and mask.dtype == bool and not mask.any()


@pytest.mark.parametrize(
    ("image", "spacing", "message"),
    [
        (np.zeros((4, 4), np.uint8), (1, 1, 1), "3-D"),
        (np.zeros((2, 4, 4), np.float32), (1, 1, 1), "uint8"),
        (np.zeros((0, 4, 4), np.uint8), (1, 1, 1), "empty volume"),
        (np.zeros((2, 4, 4), np.uint8), (1, 1), "three positive"),
        (np.zeros((2, 4, 4), np.uint8), (1, 0, 1), "three positive"),
        (np.zeros((2, 4, 4), np.uint8), (1, float("nan"), 1), "three positive"),
        (np.zeros((2, 4, 4), np.uint8), "abc", "three numbers"),
    ],
)
def test_bad_input_raises(image, spacing, message):
    with pytest.raises(InputError, match=message):
        extract_brain(image, spacing)


def test_preprocess_head_option_uses_the_extraction_and_needs_the_spacing():
    # brain_extraction="head" of preprocess_volume is this extraction, on the
    # 8-bit image the pipeline works on, and says so; without the spacing it is a
    # clear error
    from tumor3d.imaging.preprocess import preprocess_volume

    spacing = (6.5, 0.8, 0.8)
    image, brain, scalp = _head(spacing)
    out = preprocess_volume(image, brain_extraction="head", spacing_mm=spacing)
    assert out.brain_extraction == "head"
    np.testing.assert_array_equal(out.brain_mask, extract_brain(out.original_u8, spacing))
    assert _dice(out.brain_mask, brain) > 0.9 and not (out.brain_mask & scalp).any()
    # the synthetic air is exactly 0, so the auto rule takes it for skull-stripped
    assert preprocess_volume(image, spacing_mm=spacing).brain_extraction == "foreground"
    strip = preprocess_volume(image, brain_extraction="skull_strip", spacing_mm=spacing)
    assert strip.brain_extraction == "skull_strip"
    with pytest.raises(InputError, match="'head' needs the voxel spacing"):
        preprocess_volume(image, brain_extraction="head")
    with pytest.raises(InputError, match="spacing_mm must be three positive numbers"):
        preprocess_volume(image, brain_extraction="head", spacing_mm=(6.5, 0.0, 0.8))
