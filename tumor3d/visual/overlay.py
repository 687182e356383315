"""Slice overlays: a mosaic of the acquired slices with a mask contour drawn over them.

:func:`overlay_mosaic` lays the slices of a ``(z, y, x)`` volume out on a
grid of tiles, draws the boundary of a mask (the tumour, or the brain mask
of skull removal) over each, frames the slices flagged abnormal, and labels
every tile with its index and its position in mm, so that a segmentation or
skull-removal failure is visible at a glance. Pure: arrays in, an RGB array
out (the caller writes the PNG).

Tile geometry
-------------
Each slice is shown in radiological orientation, whatever the storage
order: a voxel axis whose dominant world component points to R, A or S is
flipped, so that image columns run towards the patient's left (axial,
coronal) or posterior (sagittal) and image rows towards posterior (axial)
or inferior (coronal, sagittal); an RAS- and an LPS-stored volume give the
same mosaic. The slice is then resampled by nearest neighbour to ``tile_px`` pixels
along its longer side with the in-plane pixel spacing honoured (the column
lengths of the affine), so non-square pixels do not distort the anatomy.
The intensity window is the 0.5-99.5 percentile range of the whole volume
(one window for all slices, so slices can be compared).

The patient directions at the tiles' edges (e.g. ``left R, right L, top A,
bottom P`` for axial slices) are written on the mosaic's title line and
returned in :attr:`MosaicLayout.edges`, so that the display convention
is never guessed.

The contour is the inner boundary of the mask *at tile resolution*: tile
pixels inside the resampled mask within ``contour_px`` 4-neighbour steps of a
pixel outside it, drawn in ``contour_rgb``.

Which slices and which part of them: ``slices`` chooses the slices shown (a
tile keeps its slice's index in its label), ``crop_mask`` crops every tile to
the in-plane bounding box of that mask over the shown slices plus
``crop_margin`` voxels (e.g. the brain: the air and the head's edge are left
out and the brain fills the tile). Slice position: the RAS coordinate of the slice centre
along the world axis closest to the slice normal, written with that axis's
letter, e.g. ``S +12.5 mm`` for axial slices.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from tumor3d.errors import InputError

__all__ = ["MosaicLayout", "overlay_mosaic", "slice_positions_mm"]

_HEADER_FRACTION = 0.12
_GAP_PX = 4
_ABNORMAL_RGB = (255, 170, 0)
_BACKGROUND_RGB = (24, 24, 24)
_TEXT_RGB = (235, 235, 235)


@dataclass(frozen=True)
class MosaicLayout:
    """Where each slice went in the mosaic.

    Attributes
    ----------
    tiles : tuple of (int, int, int, int)
        Per slice, the image box ``(row0, col0, row1, col1)`` (end
        exclusive) of the slice picture, below its header.
    labels : tuple of str
        Per slice, the header text (index, position, ``abnormal`` mark).
    positions_mm : tuple of float
        Per slice, the signed position along the labelled axis in mm.
    axis_letter : str
        The letter of that axis (``R``, ``A`` or ``S``).
    edges : str
        The patient directions at a tile's left, right, top and bottom edges,
        e.g. ``"RLAP"`` (axial, radiological: the patient's right on the left).
    slice_indices : tuple of int
        Per tile, the index of its slice in the volume (all slices unless
        ``slices`` chose some).
    crop_yx : tuple of int
        The in-plane voxel box ``(y0, x0, y1, x1)`` (end exclusive, in the
        volume's storage order) shown in every tile.
    """

    tiles: tuple[tuple[int, int, int, int], ...]
    labels: tuple[str, ...]
    positions_mm: tuple[float, ...]
    axis_letter: str
    edges: str = ""
    slice_indices: tuple[int, ...] = ()
    crop_yx: tuple[int, int, int, int] = (0, 0, 0, 0)


def slice_positions_mm(affine: np.ndarray, shape_zyx: Sequence[int]) -> tuple[str, np.ndarray]:
    """Position of each slice centre along the world axis nearest the slice normal.

    Parameters
    ----------
    affine : (4, 4) array_like
        Voxel index ``(x, y, z, 1)`` -> RAS mm.
    shape_zyx : sequence of 3 int
        Volume shape ``(z, y, x)``.

    Returns
    -------
    letter : str
        ``R``, ``A`` or ``S``: the world axis with the largest component of
        the slice normal (the affine's z column).
    positions_mm : (z,) float64 ndarray
        RAS coordinate of each slice centre along that axis, in mm.
    """
    aff = _check_affine(affine)
    nz, ny, nx = (int(s) for s in shape_zyx)
    axis = int(np.argmax(np.abs(aff[:3, 2])))
    k = np.arange(nz, dtype=np.float64)
    centre = np.stack(
        [np.full(nz, (nx - 1) / 2.0), np.full(nz, (ny - 1) / 2.0), k, np.ones(nz)], axis=1
    )
    ras = centre @ aff.T
    return "RAS"[axis], ras[:, axis]


def _check_affine(affine: np.ndarray) -> np.ndarray:
    try:
        aff = np.asarray(affine, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"affine must be a 4x4 numeric array, got {affine!r}") from None
    if aff.shape != (4, 4) or not np.all(np.isfinite(aff)):
        raise InputError(f"affine must be a finite 4x4 array, got shape {aff.shape}")
    if abs(np.linalg.det(aff[:3, :3])) < 1e-12:
        raise InputError("affine is singular (its 3x3 part has zero determinant)")
    return aff


def overlay_mosaic(
    image: np.ndarray,
    mask: np.ndarray,
    affine: np.ndarray,
    *,
    abnormal_slices: Sequence[int] | np.ndarray | None = None,
    contour_rgb: Sequence[int] = (255, 40, 40),
    tile_px: int = 192,
    columns: int | None = None,
    title: str | None = None,
    return_layout: bool = False,
    slices: Sequence[int] | np.ndarray | None = None,
    crop_mask: np.ndarray | None = None,
    crop_margin: int = 2,
    contour_px: int = 1,
) -> np.ndarray | tuple[np.ndarray, MosaicLayout]:
    """Mosaic of the slices with the mask's contour, abnormal slices framed.

    Parameters
    ----------
    image : (z, y, x) array_like of real numbers
        The (preprocessed) slices.
    mask : (z, y, x) array_like of bool or 0/1
        The mask whose boundary is drawn (tumour or brain), same shape.
    affine : (4, 4) array_like
        Voxel index ``(x, y, z, 1)`` -> RAS mm; gives the pixel aspect and
        the slice positions.
    abnormal_slices : sequence of int or (z,) bool array, optional
        Slices flagged abnormal (indices, or a per-slice boolean); they get
        an orange frame and ``abnormal`` in their header.
    contour_rgb : sequence of 3 int
        Contour colour, 0-255.
    tile_px : int
        Longer side of a slice picture in pixels (32-1024).
    columns : int, optional
        Tiles per mosaic row; default ``ceil(sqrt(z))``.
    title : str, optional
        A line of text above the mosaic (e.g. the patient and mask name); the
        patient directions at the tiles' edges follow it on that line.
    return_layout : bool
        Also return the :class:`MosaicLayout`.
    slices : sequence of int or (z,) bool array, optional
        The slices shown, in volume order (default all); an empty choice shows all.
    crop_mask : (z, y, x) array_like of bool or 0/1, optional
        Crop every tile to this mask's in-plane bounding box over the shown
        slices, widened by ``crop_margin`` voxels (an empty mask: no crop).
    crop_margin : int
        Voxels kept around the crop box on each side (0-64).
    contour_px : int
        Contour thickness in tile pixels (1-8).

    Returns
    -------
    mosaic : (H, W, 3) uint8 ndarray
    layout : MosaicLayout
        Only with ``return_layout=True``.

    Raises
    ------
    InputError
        On mismatched shapes, a non-3-D image, bad indices or parameters.
    """
    img = np.asarray(image)
    if img.ndim != 3 or img.size == 0:
        raise InputError(f"image must be a non-empty (z, y, x) volume, got shape {img.shape}")
    if not (np.issubdtype(img.dtype, np.number) and not np.iscomplexobj(img)):
        raise InputError(f"image must be real-valued, got dtype {img.dtype}")
    m = np.asarray(mask)
    if m.shape != img.shape:
        raise InputError(f"mask shape {m.shape} does not match image shape {img.shape}")
    m = _bool_mask(m, "mask")
    aff = _check_affine(affine)
    nz = img.shape[0]
    shown = _chosen_slices(slices, nz)
    crop = None
    if crop_mask is not None:
        c = np.asarray(crop_mask)
        if c.shape != img.shape:
            raise InputError(f"crop_mask shape {c.shape} does not match image shape {img.shape}")
        crop = _bool_mask(c, "crop_mask")
    for name, value, hi in (("crop_margin", crop_margin, 64), ("contour_px", contour_px, 8)):
        low = 1 if name == "contour_px" else 0
        if (
            isinstance(value, bool)
            or not isinstance(value, (int, np.integer))
            or not low <= value <= hi
        ):
            raise InputError(f"{name} must be an integer in [{low}, {hi}], got {value!r}")
    flags = np.zeros(nz, dtype=bool)
    if abnormal_slices is not None:
        ab = np.asarray(abnormal_slices)
        if ab.dtype == bool:
            if ab.shape != (nz,):
                raise InputError(f"abnormal_slices as booleans must have shape ({nz},)")
            flags = ab.copy()
        else:
            if ab.size and (
                not np.issubdtype(ab.dtype, np.integer) or ab.min() < 0 or ab.max() >= nz
            ):
                raise InputError(f"abnormal_slices must be slice indices in [0, {nz})")
            flags[ab.astype(np.int64).ravel()] = True
    rgb = np.asarray(contour_rgb)
    if (
        rgb.shape != (3,)
        or not np.issubdtype(rgb.dtype, np.integer)
        or rgb.min() < 0
        or (rgb.max() > 255)
    ):
        raise InputError(f"contour_rgb must be 3 integers in [0, 255], got {contour_rgb!r}")
    if (
        isinstance(tile_px, bool)
        or not isinstance(tile_px, (int, np.integer))
        or not (32 <= tile_px <= 1024)
    ):
        raise InputError(f"tile_px must be an integer in [32, 1024], got {tile_px!r}")
    if columns is None:
        columns = math.ceil(math.sqrt(len(shown)))
    elif isinstance(columns, bool) or not isinstance(columns, (int, np.integer)) or columns < 1:
        raise InputError(f"columns must be a positive integer, got {columns!r}")
    if title is not None and not isinstance(title, str):
        raise InputError(f"title must be a string, got {type(title).__name__}")
    y0, x0, y1, x1 = 0, 0, img.shape[1], img.shape[2]
    if crop is not None and crop[shown].any():
        ys = np.flatnonzero(crop[shown].any(axis=(0, 2)))
        xs = np.flatnonzero(crop[shown].any(axis=(0, 1)))
        y0, y1 = max(0, ys[0] - crop_margin), min(img.shape[1], ys[-1] + 1 + crop_margin)
        x0, x1 = max(0, xs[0] - crop_margin), min(img.shape[2], xs[-1] + 1 + crop_margin)
    # one intensity window for the whole volume, before choosing and cropping
    gray = _window(img)
    gray, m = gray[shown, y0:y1, x0:x1], m[shown, y0:y1, x0:x1]
    flags = flags[shown]
    # radiological display: flip in-plane voxel axes that point to R, A or S
    flip_x = aff[int(np.argmax(np.abs(aff[:3, 0]))), 0] > 0
    flip_y = aff[int(np.argmax(np.abs(aff[:3, 1]))), 1] > 0
    if flip_x:
        gray, m = gray[:, :, ::-1], m[:, :, ::-1]
    if flip_y:
        gray, m = gray[:, ::-1, :], m[:, ::-1, :]
    edges = _edge_letters(aff[:3, 0] * (-1.0 if flip_x else 1.0)) + _edge_letters(
        aff[:3, 1] * (-1.0 if flip_y else 1.0)
    )
    letter, pos = slice_positions_mm(aff, img.shape)
    mosaic, layout = _compose(
        gray, m, aff, flags, tuple(int(c) for c in rgb), int(tile_px), int(columns), title,
        edges, index=shown, letter=letter, positions=pos[shown], contour_px=int(contour_px),
    )  # fmt: skip
    layout = replace(layout, crop_yx=(int(y0), int(x0), int(y1), int(x1)))
    return (mosaic, layout) if return_layout else mosaic


def _bool_mask(m: np.ndarray, name: str) -> np.ndarray:
    if m.dtype == bool:
        return m
    if not np.issubdtype(m.dtype, np.number) or not np.isin(m, (0, 1)).all():
        raise InputError(f"{name} must be boolean or contain only 0 and 1")
    return m.astype(bool)


def _chosen_slices(slices: Sequence[int] | np.ndarray | None, nz: int) -> np.ndarray:
    """The indices of the shown slices, sorted (all when ``slices`` is None or empty)."""
    if slices is None:
        return np.arange(nz)
    s = np.asarray(slices)
    if s.dtype == bool:
        if s.shape != (nz,):
            raise InputError(f"slices as booleans must have shape ({nz},)")
        s = np.flatnonzero(s)
    elif s.size and (not np.issubdtype(s.dtype, np.integer) or s.min() < 0 or s.max() >= nz):
        raise InputError(f"slices must be slice indices in [0, {nz})")
    s = np.unique(s.astype(np.int64).ravel())
    return s if s.size else np.arange(nz)


def _edge_letters(direction: np.ndarray) -> str:
    """The patient directions at the low and high end of an image axis (RAS ``direction``).

    >>> _edge_letters(np.array([-1.0, 0.0, 0.0]))  # the axis runs towards the left
    'RL'
    """
    i = int(np.argmax(np.abs(direction)))
    towards = "RAS"[i] if direction[i] > 0 else "LPI"[i]
    return {"R": "L", "L": "R", "A": "P", "P": "A", "S": "I", "I": "S"}[towards] + towards


def _window(img: np.ndarray) -> np.ndarray:
    vals = img[np.isfinite(img)] if np.issubdtype(img.dtype, np.floating) else img.ravel()
    if vals.size == 0:
        return np.zeros(img.shape, dtype=np.uint8)
    lo, hi = np.percentile(vals, [0.5, 99.5])
    if hi <= lo:
        hi = lo + 1.0
    out = np.clip((np.nan_to_num(img.astype(np.float64), nan=lo) - lo) / (hi - lo), 0.0, 1.0)
    return np.rint(out * 255.0).astype(np.uint8)


def _inner_boundary(mask: np.ndarray, width: int = 1) -> np.ndarray:
    """Pixels of a 2-D mask within ``width`` 4-neighbour steps of the outside.

    The image border counts as outside.

    >>> m = np.zeros((7, 7), bool); m[1:6, 1:6] = True
    >>> int(_inner_boundary(m, 1).sum()), int(_inner_boundary(m, 2).sum())
    (16, 24)
    """
    inner = mask
    for _ in range(width):
        p = np.pad(inner, 1, constant_values=False)
        inner = p[1:-1, 1:-1] & p[1:-1, :-2] & p[1:-1, 2:] & p[:-2, 1:-1] & p[2:, 1:-1]
    return mask & ~inner


def _wrap(text: str, font: Any, width_px: int) -> list[str]:
    """``text`` in lines of at most ``width_px`` pixels in ``font``, broken between words.

    A word longer than the width keeps a line of its own.
    """
    lines: list[str] = []
    for word in text.split(" "):
        if lines and font.getlength(f"{lines[-1]} {word}") <= width_px:
            lines[-1] = f"{lines[-1]} {word}"
        else:
            lines.append(word)
    return lines or [""]


def _compose(
    gray: np.ndarray,
    mask: np.ndarray,
    aff: np.ndarray,
    flags: np.ndarray,
    contour_rgb: tuple[int, int, int],
    tile_px: int,
    columns: int,
    title: str | None,
    edges: str,
    *,
    index: np.ndarray,
    letter: str,
    positions: np.ndarray,
    contour_px: int,
) -> tuple[np.ndarray, MosaicLayout]:
    """The mosaic of the windowed (uint8) slices ``gray``; ``index`` their volume indices."""
    from PIL import Image, ImageDraw

    from tumor3d.visual.render.annotate import _font

    nz, ny, nx = gray.shape
    dx = float(np.linalg.norm(aff[:3, 0]))
    dy = float(np.linalg.norm(aff[:3, 1]))
    width_mm, height_mm = nx * dx, ny * dy
    scale = tile_px / max(width_mm, height_mm)
    tw = max(1, int(round(width_mm * scale)))
    th = max(1, int(round(height_mm * scale)))
    # nearest-neighbour sample positions (pixel centres)
    src_c = np.minimum(((np.arange(tw) + 0.5) / tw * nx).astype(np.int64), nx - 1)
    src_r = np.minimum(((np.arange(th) + 0.5) / th * ny).astype(np.int64), ny - 1)
    header = max(12, int(round(_HEADER_FRACTION * tile_px)))
    rows = math.ceil(nz / columns)
    sides = f"left {edges[0]}, right {edges[1]}, top {edges[2]}, bottom {edges[3]}"
    title = f"{title}   ({sides})" if title else sides
    cell_w, cell_h = tw + _GAP_PX, th + header + _GAP_PX
    big_w = columns * cell_w + _GAP_PX
    font = _font(max(8, int(header * 0.6)))
    # a mosaic of one or two tiles is narrower than its title: wrapped, never cut (the
    # patient directions at its end were lost)
    title_lines = _wrap(title, font, big_w - 2 * _GAP_PX)
    title_h = header * len(title_lines) + _GAP_PX
    big_h = title_h + rows * cell_h + _GAP_PX
    out = np.empty((big_h, big_w, 3), dtype=np.uint8)
    out[:] = _BACKGROUND_RGB
    pos = positions
    tiles = []
    labels = []
    frame = max(2, tile_px // 64)
    for k in range(nz):
        r0 = title_h + _GAP_PX + (k // columns) * cell_h + header
        c0 = _GAP_PX + (k % columns) * cell_w
        g = gray[k][np.ix_(src_r, src_c)]
        tile = np.repeat(g[:, :, None], 3, axis=2)
        edge = _inner_boundary(mask[k][np.ix_(src_r, src_c)], contour_px)
        tile[edge] = contour_rgb
        out[r0 : r0 + th, c0 : c0 + tw] = tile
        if flags[k]:
            out[r0 - frame : r0, c0 - frame : c0 + tw + frame] = _ABNORMAL_RGB
            out[r0 + th : r0 + th + frame, c0 - frame : c0 + tw + frame] = _ABNORMAL_RGB
            out[r0 : r0 + th, c0 - frame : c0] = _ABNORMAL_RGB
            out[r0 : r0 + th, c0 + tw : c0 + tw + frame] = _ABNORMAL_RGB
        tiles.append((r0, c0, r0 + th, c0 + tw))
        labels.append(f"#{int(index[k])} {letter} {pos[k]:+.1f} mm" + (" abn." if flags[k] else ""))
    pil = Image.fromarray(out)
    draw = ImageDraw.Draw(pil)
    for k, (r0, c0, _, _) in enumerate(tiles):
        ink = _ABNORMAL_RGB if flags[k] else _TEXT_RGB
        draw.text((c0, r0 - frame - 1), labels[k], fill=ink, font=font, anchor="lb")
    for i, line in enumerate(title_lines):
        y = _GAP_PX + i * header + header // 2
        draw.text((_GAP_PX, y), line, fill=_TEXT_RGB, font=font, anchor="lm")
    layout = MosaicLayout(
        tiles=tuple(tiles),
        labels=tuple(labels),
        positions_mm=tuple(float(p) for p in pos),
        axis_letter=letter,
        edges=edges,
        slice_indices=tuple(int(i) for i in index),
    )
    return np.asarray(pil, dtype=np.uint8).copy(), layout
