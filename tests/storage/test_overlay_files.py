"""The published overlay PNGs: brain slices only, cropped to the brain, 2-px contours (issue 33)."""

from __future__ import annotations

import io

import numpy as np
from PIL import Image

from tumor3d.storage.patient_outputs import OVERLAY_TILE_PX, write_overlays

RED = np.array((255, 40, 40), dtype=np.uint8)


def _case(nz=6, ny=60, nx=80):
    rng = np.random.default_rng(2)
    img = rng.normal(50.0, 3.0, (nz, ny, nx))
    brain = np.zeros((nz, ny, nx), dtype=bool)
    brain[1:5, 20:40, 25:61] = True  # slices 1-4; 20 rows x 36 columns of 1 mm
    tumour = np.zeros_like(brain)
    tumour[2:4, 26:34, 38:48] = True
    img[brain] += 70.0
    return img, brain, tumour, np.diag([1.0, 1.0, 4.0, 1.0])


def _png(path):
    return np.asarray(Image.open(io.BytesIO(path.read_bytes())).convert("RGB"))


def _runs(row_mask):
    """Lengths of the runs of True in a 1-D boolean array."""
    padded = np.concatenate([[False], row_mask, [False]])
    edges = np.flatnonzero(np.diff(padded.astype(np.int8)))
    return (edges[1::2] - edges[::2]).tolist()


def test_overlays_show_only_brain_slices_cropped_with_a_two_pixel_contour(tmp_path):
    img, brain, tumour, aff = _case()
    names = write_overlays(tmp_path, img, aff, brain, tumour, [2])
    assert sorted(names) == ["overlay_brain.png", "overlay_tumor.png"]
    pic = _png(tmp_path / "overlay_brain.png")
    # 4 slices with brain -> 2 x 2 tiles; the crop (36 + 2*3 columns, 20 + 2*3 rows) has
    # its longer side across: tiles OVERLAY_TILE_PX wide, 4-px gaps
    assert pic.shape[1] == 2 * (OVERLAY_TILE_PX + 4) + 4
    header = round(0.12 * OVERLAY_TILE_PX)  # a tile's label line; the title line as high
    crop_tile_h = round(26 * OVERLAY_TILE_PX / 42)  # not round(60 * ... / 80) uncropped
    # the title ("brain mask contour; 4 of 6 slices, those with brain" and the patient
    # directions) is wider than two tiles: two lines, each a label line high
    assert pic.shape[0] == (2 * header + 4) + 2 * (crop_tile_h + header + 4) + 4
    red = np.all(pic == RED, axis=2)
    # a row through the middle of a top tile crosses the brain's left and right edges:
    # two red runs of exactly 2 pixels each, in each of the two tiles of that row
    rows = np.flatnonzero(red.any(axis=1))
    top = rows.min()
    mid = top + crop_tile_h // 3  # inside the brain box (20 of the 26 rows) of the top tiles
    assert _runs(red[mid]) == [2, 2, 2, 2]
    # the tumour overlay: same layout, its own contour
    tum = _png(tmp_path / "overlay_tumor.png")
    assert tum.shape == pic.shape
    assert np.all(tum == RED, axis=2).sum() > 0


def test_without_any_brain_every_slice_is_shown_whole(tmp_path):
    img, brain, tumour, aff = _case()
    write_overlays(tmp_path, img, aff, np.zeros_like(brain), np.zeros_like(tumour), [])
    pic = _png(tmp_path / "overlay_brain.png")
    # 6 slices -> 3 columns of whole (80-voxel-wide) slices
    assert pic.shape[1] == 3 * (OVERLAY_TILE_PX + 4) + 4


def test_a_narrow_mosaic_wraps_its_title_instead_of_cutting_it(tmp_path):
    """Two tiles are narrower than the title: it is wrapped, not cut at the right edge
    (the patient directions at its end were cut off)."""
    img, brain, tumour, aff = _case()
    brain[3:] = False  # brain on slices 1 and 2 only: two tiles
    write_overlays(tmp_path, img, aff, brain, tumour & brain, [2])
    pic = _png(tmp_path / "overlay_tumor.png")
    assert pic.shape[1] == 2 * (OVERLAY_TILE_PX + 4) + 4
    header = round(0.12 * OVERLAY_TILE_PX)
    band = pic[: 2 * header]  # the title's lines
    background = band[0, 0]
    ink = np.any(band != background, axis=2)
    assert ink.any() and not ink[:, -4:].any()  # written, and clear of the right edge
