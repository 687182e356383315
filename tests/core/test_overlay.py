"""Tests of tumor3d.visual.overlay: slice mosaics with mask contours."""

from __future__ import annotations

import numpy as np
import pytest

from tumor3d.errors import InputError
from tumor3d.visual.overlay import overlay_mosaic, slice_positions_mm

RED = (255, 40, 40)


def _volume(nz=5, ny=40, nx=60):
    rng = np.random.default_rng(0)
    img = rng.normal(100.0, 5.0, (nz, ny, nx))
    mask = np.zeros((nz, ny, nx), dtype=bool)
    mask[2, 10:20, 30:50] = True  # a 10 x 20 pixel rectangle on slice 2
    img[mask] = 200.0
    aff = np.diag([0.5, 0.5, 5.0, 1.0])
    aff[:3, 3] = (-15.0, -10.0, -10.0)
    return img, mask, aff


def _is(rgb_img, colour):
    return np.all(rgb_img == np.array(colour, dtype=np.uint8), axis=2)


def test_contour_is_the_mask_boundary_in_the_right_tile():
    img, mask, aff = _volume()
    mosaic, layout = overlay_mosaic(img, mask, aff, tile_px=120, return_layout=True)
    assert mosaic.dtype == np.uint8 and mosaic.ndim == 3
    red = _is(mosaic, RED)
    r0, c0, r1, c1 = layout.tiles[2]
    assert (r1 - r0, c1 - c0) == (80, 120)  # 60 x 40 pixels of 0.5 mm: aspect kept, x2
    inside = red[r0:r1, c0:c1]
    assert red.sum() == inside.sum()  # contour only on slice 2
    # independent expectation: the rectangle rows 10-19, cols 30-49, shown radiologically
    # (the RAS-stored x and y axes flipped: rows 20-29, cols 10-29), scaled x2 -> its outline
    rows, cols = np.nonzero(inside)
    assert (rows.min(), rows.max(), cols.min(), cols.max()) == (40, 59, 20, 59)
    want = np.zeros((80, 120), dtype=bool)
    want[40:60, 20:60] = True
    want[41:59, 21:59] = False
    assert np.array_equal(inside, want)


def test_ras_and_lps_storage_give_the_same_mosaic():
    img, mask, aff = _volume()
    nz, ny, nx = img.shape
    # the same voxels stored with x and y reversed (LPS): index i -> n - 1 - i
    lps = aff @ np.array([[-1, 0, 0, nx - 1], [0, -1, 0, ny - 1], [0, 0, 1, 0], [0, 0, 0, 1]])
    a = overlay_mosaic(img, mask, aff, abnormal_slices=[2])
    b = overlay_mosaic(img[:, ::-1, ::-1], mask[:, ::-1, ::-1], lps, abnormal_slices=[2])
    assert np.array_equal(a, b)
    assert lps[0, 0] < 0 < aff[0, 0]  # the two storage orders really differ


def test_abnormal_slices_are_framed_and_labelled():
    img, mask, aff = _volume()
    mosaic, layout = overlay_mosaic(
        img, mask, aff, abnormal_slices=[1, 2], tile_px=120, return_layout=True
    )
    orange = _is(mosaic, (255, 170, 0))
    for k, (_r0, c0, r1, c1) in enumerate(layout.tiles):
        framed = orange[r1 : r1 + 2, c0:c1].all()  # the frame below the tile
        assert framed == (k in (1, 2)), k
        assert layout.labels[k].endswith("abn.") == (k in (1, 2))
    same = overlay_mosaic(
        img, mask, aff, abnormal_slices=np.isin(np.arange(5), [1, 2]), tile_px=120
    )
    assert np.array_equal(mosaic, same)


def test_slice_positions_in_mm_are_labelled():
    img, mask, aff = _volume()
    _, layout = overlay_mosaic(img, mask, aff, return_layout=True)
    # slice centre z = -10 + 5 k mm (axial: S axis)
    assert layout.axis_letter == "S"
    np.testing.assert_allclose(layout.positions_mm, [-10.0, -5.0, 0.0, 5.0, 10.0])
    assert layout.labels[0] == "#0 S -10.0 mm" and layout.labels[3] == "#3 S +5.0 mm"


def test_positions_of_sagittal_slices_follow_the_world_axis():
    # slice axis along -x (R->L): each voxel z step moves 3 mm to the left
    aff = np.array([[0, 0, -3.0, 40.0], [1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 0, 1]])
    letter, pos = slice_positions_mm(aff, (4, 10, 10))
    assert letter == "R"
    np.testing.assert_allclose(pos, [40.0, 37.0, 34.0, 31.0])


def test_brain_mask_leak_is_visible():
    # a brain mask that spills over the whole slice (skull not removed) on slice 4
    img, _, aff = _volume()
    brain = np.zeros(img.shape, dtype=bool)
    brain[:, 5:35, 10:50] = True
    brain[4] = True
    mosaic, layout = overlay_mosaic(
        img, brain, aff, contour_rgb=(0, 200, 255), tile_px=120, return_layout=True
    )
    cyan = _is(mosaic, (0, 200, 255))
    r0, c0, r1, c1 = layout.tiles[4]
    tile = cyan[r0:r1, c0:c1]
    # the contour runs along the tile border on the leaking slice
    assert tile[0].all() and tile[-1].all() and tile[:, 0].all() and tile[:, -1].all()
    r0, c0, r1, c1 = layout.tiles[0]
    assert not cyan[r0:r1, c0:c1][0].any()


def test_image_is_not_modified_and_greys_are_windowed():
    img, mask, aff = _volume()
    before = img.copy()
    mosaic, layout = overlay_mosaic(img, mask, aff, tile_px=60, return_layout=True)
    assert np.array_equal(img, before)
    r0, c0, r1, c1 = layout.tiles[2]
    tile = mosaic[r0:r1, c0:c1]
    # radiological flips of both in-plane axes: voxel (y, x) -> tile (ny - 1 - y, nx - 1 - x)
    assert np.all(tile[40 - 1 - 15, 60 - 1 - 40] == 255)  # the bright rectangle saturates
    # one window for the volume: 0.5-99.5 percentiles mapped to 0-255
    lo, hi = np.percentile(img, [0.5, 99.5])
    want = np.clip(np.rint((img[2, 40 - 1 - 2, 60 - 1 - 2] - lo) / (hi - lo) * 255), 0, 255)
    assert abs(int(tile[2, 2, 0]) - want) <= 1


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"mask": np.zeros((5, 40, 59), bool)}, "mask shape"),
        ({"mask": np.full((5, 40, 60), 2)}, "only 0 and 1"),
        ({"affine": np.eye(3)}, "4x4"),
        ({"affine": np.zeros((4, 4))}, "singular"),
        ({"abnormal_slices": [5]}, r"indices in \[0, 5\)"),
        ({"abnormal_slices": np.ones(4, bool)}, r"shape \(5,\)"),
        ({"contour_rgb": (300, 0, 0)}, "contour_rgb"),
        ({"tile_px": 8}, "tile_px"),
        ({"columns": 0}, "columns"),
        ({"image": np.zeros((40, 60))}, "volume"),
    ],
)
def test_validation(kwargs, match):
    img, mask, aff = _volume()
    args = {"image": img, "mask": mask, "affine": aff, **kwargs}
    with pytest.raises(InputError, match=match):
        overlay_mosaic(args.pop("image"), args.pop("mask"), args.pop("affine"), **args)


@pytest.mark.parametrize(
    "affine, edges",
    [
        (np.diag([0.5, 0.5, 5.0, 1.0]), "RLAP"),  # RAS storage, axial: radiological
        (np.diag([-0.5, -0.5, 5.0, 1.0]), "RLAP"),  # LPS storage: the same display
        # coronal slices: columns along x (R), rows along -z (inferior), slices along y
        (np.array([[1.0, 0, 0, 0], [0, 0, 4.0, 0], [0, -1.0, 0, 0], [0, 0, 0, 1]]), "RLSI"),
        # sagittal slices: columns along y (A), rows along z (S), slices along x
        (np.array([[0, 0, 3.0, 0], [1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 0, 1]]), "APSI"),
    ],
)
def test_the_tiles_edges_are_named_by_patient_direction(affine, edges):
    img, mask, _ = _volume()
    _, layout = overlay_mosaic(img, mask, affine, title="t", return_layout=True)
    assert layout.edges == edges
    # independent check: the voxel shown at a tile's left column lies farther towards
    # the left-edge direction than the one at its right column (world coordinates)
    letters = {"R": (0, 1), "L": (0, -1), "A": (1, 1), "P": (1, -1), "S": (2, 1), "I": (2, -1)}
    axis, sign = letters[edges[0]]
    col = affine[:3, 0]
    flipped = affine[int(np.argmax(np.abs(col))), 0] > 0  # the display flips such an axis
    first, last = (img.shape[2] - 1, 0) if flipped else (0, img.shape[2] - 1)
    assert sign * (affine[axis, 0] * first - affine[axis, 0] * last) > 0
