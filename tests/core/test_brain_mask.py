"""tumor3d.imaging.brain_mask: the rules of a given brain mask.

Grid, brain = values > 0.5, refusals.
"""

from __future__ import annotations

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.imaging.brain_mask import (
    GRID_TOL_VOXELS,
    binarize_brain_mask,
    check_same_grid,
    grid_offset_voxels,
)


@pytest.fixture
def head():
    """A bright 'head' block in a noisy dark background, and its brain block."""
    rng = np.random.default_rng(3)
    image = rng.random((6, 20, 20)).astype(np.float32) * 30  # air with noise
    image[:, 4:16, 4:16] += 500
    brain = np.zeros(image.shape, bool)
    brain[:, 6:14, 6:14] = True
    return image, brain


@pytest.mark.parametrize(
    "encode",
    [
        lambda b: b.astype(np.uint8),  # 0/1
        lambda b: b.astype(np.uint8) * 255,  # 0/255
        lambda b: np.where(b, 0.9, 0.2).astype(np.float32),  # probability map
        lambda b: b,  # bool
    ],
    ids=["binary", "0-255", "probability", "bool"],
)
def test_every_mask_encoding_gives_the_same_brain(head, encode):
    image, brain = head
    np.testing.assert_array_equal(binarize_brain_mask(encode(brain), image), brain)


def test_brain_is_strictly_above_one_half(head):
    image, brain = head
    values = np.where(brain, 0.5, 0.0).astype(np.float32)
    values[0, 8, 8] = 0.5001
    got = binarize_brain_mask(values, image)
    assert got.sum() == 1 and got[0, 8, 8]


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda b: np.zeros(b.shape, np.uint8), r"empty: no voxel is above 0\.5"),
        (lambda b: np.where(b, 0.5, 0.0), r"empty: .*largest value 0\.5"),
        (
            lambda b: np.where(b, np.nan, 1.0).astype(np.float32),
            r"384 of 2400 voxel values are not finite \(384 NaN, 0 infinite\)",
        ),
        (lambda b: np.where(b, np.inf, 0.0), r"not finite \(0 NaN, 384 infinite\)"),
    ],
    ids=["zeros", "all-half", "nan", "inf"],
)
def test_refused_values(head, make, message):
    image, brain = head
    with pytest.raises(InputError, match=message):
        binarize_brain_mask(make(brain), image)


def test_a_mask_off_the_head_is_refused(head):
    image, _ = head
    corner = np.zeros(image.shape, bool)
    corner[:, :3, :3] = True  # only air (noise up to 30; the head is 500+)
    with pytest.raises(InputError, match=r"no overlap with the image: none of its 54 brain"):
        binarize_brain_mask(corner, image)
    corner[0, 10, 10] = True  # one voxel on the head is enough
    assert binarize_brain_mask(corner, image).sum() == 55


def test_same_grid_within_tolerance_passes_and_names_both_otherwise():
    aff = np.array([[-0.9, 0, 0, 90], [0, 0.9, 0, -120], [0, 0, 5, -40], [0, 0, 0, 1.0]])
    check_same_grid((10, 10, 4), aff, (10, 10, 4), aff)
    nudged = aff.copy()
    nudged[0, 3] += 0.9 * GRID_TOL_VOXELS / 2  # half the tolerance
    check_same_grid((10, 10, 4), nudged, (10, 10, 4), aff)
    with pytest.raises(InputError, match=r"shape \(10, 10, 5\) differs from the image's "
                       r"\(10, 10, 4\)"):  # fmt: skip
        check_same_grid((10, 10, 5), aff, (10, 10, 4), aff)
    moved = aff.copy()
    moved[2, 3] += 2.5  # half a slice
    with pytest.raises(InputError) as info:
        check_same_grid((10, 10, 4), moved, (10, 10, 4), aff)
    text = str(info.value)
    assert "affine [-0.9 0 0 90; 0 0.9 0 -120; 0 0 5 -37.5]" in text
    assert "the image's [-0.9 0 0 90; 0 0.9 0 -120; 0 0 5 -40]" in text
    assert "0.5 voxels apart" in text


def test_grid_offset_counts_voxels_of_the_image_grid():
    aff = np.diag([2.0, 2.0, 5.0, 1.0])
    flipped = aff.copy()
    flipped[0, 0], flipped[0, 3] = -2.0, 18.0  # x reversed: corners 9 voxels off
    assert grid_offset_voxels((10, 4, 4), aff, aff) == 0.0
    assert grid_offset_voxels((10, 4, 4), flipped, aff) == pytest.approx(9.0)
