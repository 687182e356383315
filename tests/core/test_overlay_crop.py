"""Overlay mosaics cropped to a region, with chosen slices and a thicker contour (issue 33)."""

from __future__ import annotations

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.visual.overlay import overlay_mosaic

RED = (255, 40, 40)


def _head(nz=6, ny=60, nx=80):
    """A 'brain' box on slices 1-4 in a larger field of view, a square 'tumour' on slice 3."""
    rng = np.random.default_rng(1)
    img = rng.normal(50.0, 3.0, (nz, ny, nx))
    brain = np.zeros((nz, ny, nx), dtype=bool)
    brain[1:5, 20:40, 30:60] = True  # 20 rows x 30 columns
    tumour = np.zeros_like(brain)
    tumour[3, 25:35, 40:50] = True
    img[brain] = 120.0
    img[tumour] = 200.0
    aff = np.diag([1.0, 1.0, 4.0, 1.0])
    return img, brain, tumour, aff


def _red(a):
    return np.all(a == np.array(RED, dtype=np.uint8), axis=2)


def test_only_the_chosen_slices_are_shown_with_their_own_indices():
    img, brain, tumour, aff = _head()
    shown = brain.any(axis=(1, 2))
    _, layout = overlay_mosaic(img, tumour, aff, slices=shown, return_layout=True)
    assert layout.slice_indices == (1, 2, 3, 4)  # slices 0 and 5 have no brain
    assert len(layout.tiles) == 4
    assert [lab.split()[0] for lab in layout.labels] == ["#1", "#2", "#3", "#4"]
    _, every = overlay_mosaic(img, tumour, aff, return_layout=True)
    assert every.slice_indices == tuple(range(6))
    # the shown tiles keep their slice's position in mm
    assert layout.positions_mm == tuple(every.positions_mm[k] for k in (1, 2, 3, 4))


def test_tiles_are_cropped_to_the_region_box_plus_margin():
    img, brain, tumour, aff = _head()
    _, layout = overlay_mosaic(
        img, tumour, aff, crop_mask=brain, crop_margin=2, tile_px=120, return_layout=True
    )
    assert layout.crop_yx == (18, 28, 42, 62)  # rows 20-39, columns 30-59, 2 voxels around
    r0, c0, r1, c1 = layout.tiles[0]
    # 34 x 24 voxels of 1 mm: the longer side is 120 px, the aspect kept
    assert (c1 - c0, r1 - r0) == (120, round(24 * 120 / 34))
    _, whole = overlay_mosaic(img, tumour, aff, tile_px=120, return_layout=True)
    assert whole.crop_yx == (0, 0, 60, 80)
    # the cropped tile shows the brain larger: the tumour's outline spans more pixels
    crop_img = overlay_mosaic(img, tumour, aff, crop_mask=brain, crop_margin=2, tile_px=120)
    whole_img = overlay_mosaic(img, tumour, aff, tile_px=120)
    assert np.ptp(np.nonzero(_red(crop_img))[1]) > 2 * np.ptp(np.nonzero(_red(whole_img))[1])


def test_an_empty_crop_mask_keeps_the_whole_slice():
    img, brain, tumour, aff = _head()
    _, layout = overlay_mosaic(img, tumour, aff, crop_mask=np.zeros_like(brain), return_layout=True)
    assert layout.crop_yx == (0, 0, 60, 80)


def test_the_contour_is_as_wide_as_asked():
    img, brain, tumour, aff = _head()
    # tile 80 px for 80 voxels: one tile pixel per voxel; the 10 x 10 square on slice 3
    one = overlay_mosaic(img, tumour, aff, tile_px=80, contour_px=1)
    two = overlay_mosaic(img, tumour, aff, tile_px=80, contour_px=2)
    assert _red(one).sum() == 10 * 10 - 8 * 8  # the square's 1-pixel ring
    assert _red(two).sum() == 10 * 10 - 6 * 6  # its 2-pixel ring


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"contour_px": 0}, "contour_px must be an integer in \\[1, 8\\]"),
        ({"contour_px": 2.0}, "contour_px must be an integer"),
        ({"crop_margin": -1}, "crop_margin must be an integer in \\[0, 64\\]"),
        ({"slices": [6]}, "slices must be slice indices in \\[0, 6\\)"),
        ({"slices": np.ones(5, bool)}, "slices as booleans must have shape \\(6,\\)"),
        ({"crop_mask": np.zeros((6, 60, 79), bool)}, "crop_mask shape"),
        ({"crop_mask": np.full((6, 60, 80), 2)}, "crop_mask must be boolean"),
    ],
)
def test_validation_of_the_new_options(kwargs, match):
    img, _, tumour, aff = _head()
    with pytest.raises(InputError, match=match):
        overlay_mosaic(img, tumour, aff, **kwargs)
