"""In-plane mask morphology of the stack: bounding boxes, hole filling, the foreground brain.

The brain mask of an input already skull-stripped is its non-zero
foreground (:func:`foreground_brain_mask`).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from tumor3d.errors import InputError
from tumor3d.imaging.preprocess.intensity import _check_volume, masked_background


def _in_plane(footprint: np.ndarray) -> np.ndarray:
    """A 2-D footprint as a ``(1, h, w)`` structure: it never links slices."""
    return np.asarray(footprint, dtype=bool)[None]


def foreground_brain_mask(image: np.ndarray) -> np.ndarray:
    """Brain mask of an already skull-stripped volume: its foreground.

    Foreground = voxels that differ from the constant masked background
    (:func:`masked_background`, whatever its value: 0, negative for z-scored
    volumes, or 0 below a brain with negative values too); the largest
    26-connected 3-D component is kept (stray background specks drop out)
    and each slice's holes are filled (dark necrosis or ventricles whose
    intensity equals the background). Nothing is eroded, so the brain's rim,
    where a tumour may touch the surface, stays in.

    Parameters
    ----------
    image : (z, y, x) ndarray of real numbers

    Returns
    -------
    (z, y, x) ndarray of bool
        Empty if the volume is constant.
    """
    return _foreground_brain_mask(_check_volume(image))


def _foreground_brain_mask(arr: np.ndarray, background=None) -> np.ndarray:
    bg = masked_background(arr) if background is None else background
    fg = ~bg.mask
    box = true_box(fg)
    if box is None:
        return fg
    # Components, their sizes and their raster order (argmax's tie-break) are the same
    # on the bounding box of the foreground as on the whole volume.
    sub = fg[box]
    labels, n = ndi.label(sub, structure=np.ones((3, 3, 3), dtype=bool))
    if n > 1:
        sizes = np.bincount(labels.ravel())
        sizes[0] = 0
        sub = labels == int(np.argmax(sizes))
        # the largest component may have a smaller box: hole filling works on that one
        fg = np.zeros_like(fg)
        fg[box] = sub
    return fill_holes_per_slice(fg)


def true_box(mask: np.ndarray) -> tuple[slice, ...] | None:
    """Bounding box (all three axes) of the True voxels of a 3-D mask, or None.

    >>> m = np.zeros((3, 6, 6), bool); m[1, 2:4, 1:5] = True
    >>> [(int(s.start), int(s.stop)) for s in true_box(m)]
    [(1, 2), (2, 4), (1, 5)]
    """
    zs = np.flatnonzero(mask.any(axis=(1, 2)))
    if zs.size == 0:
        return None
    ys = np.flatnonzero(mask.any(axis=(0, 2)))
    xs = np.flatnonzero(mask.any(axis=(0, 1)))
    return (
        slice(zs[0], zs[-1] + 1),
        slice(ys[0], ys[-1] + 1),
        slice(xs[0], xs[-1] + 1),
    )


#: 4-connectivity in the (y, x) plane and no link between slices.
_IN_PLANE_4 = np.zeros((3, 3, 3), dtype=bool)
_IN_PLANE_4[1] = ndi.generate_binary_structure(2, 1)


def fill_holes_per_slice(mask: np.ndarray) -> np.ndarray:
    """Fill the holes of every ``(y, x)`` slice of a ``(z, y, x)`` mask in one call.

    Same result as ``scipy.ndimage.binary_fill_holes`` of each slice (holes =
    background pixels not 4-connected to the slice border). The background of
    the mask's bounding box, framed by a one-pixel ring of background that
    stands for everything outside the box (background on every slice, hence
    connected to the border), is labelled once with a structuring element
    that links 4-neighbours within a slice and never across slices; every
    background component other than the ring's own is a hole.

    Examples
    --------
    >>> ring = np.ones((1, 5, 5), dtype=bool); ring[0, 2, 2] = False
    >>> bool(fill_holes_per_slice(ring)[0, 2, 2])
    True
    """
    mask = np.asarray(mask, dtype=bool)
    if mask.ndim != 3:
        raise InputError("fill_holes_per_slice needs a 3-D (z, y, x) mask")
    out = mask.copy()
    box = true_box(mask)
    if box is None:
        return out
    background = np.pad(~mask[box], ((0, 0), (1, 1), (1, 1)), constant_values=True)
    labels, _ = ndi.label(background, structure=_IN_PLANE_4)
    outside = labels[:, :1, :1]  # the ring's component, one per slice
    holes = labels[:, 1:-1, 1:-1]
    out[box] |= (holes != outside) & (holes > 0)
    return out
