"""A brain mask given by the user instead of the one skull removal finds.

The rules (pure: arrays in, arrays out; reading the file is
:mod:`tumor3d.storage.brain_mask`'s):

* **Grid.** The mask must lie on the image's voxel grid: the same shape and
  an affine that places every voxel centre within :data:`GRID_TOL_VOXELS`
  of a voxel (:func:`check_same_grid`). Nothing is resampled.
* **Brain** = voxels whose value is ``> 0.5`` (:data:`BRAIN_THRESHOLD`), so a
  binary 0/1 mask, a 0/255 mask and a probability map all work
  (:func:`binarize_brain_mask`).
* **Refused:** non-finite values, an empty mask (no voxel > 0.5), and a
  mask with no voxel on the image's non-background (voxels above the
  image's Otsu threshold, which separates the air, noise included, from
  the head): such a mask belongs to another image or is misplaced.
"""

from __future__ import annotations

import numpy as np
from skimage.filters import threshold_otsu

from tumor3d.errors import InputError
from tumor3d.validation import non_finite_problem

__all__ = [
    "BRAIN_THRESHOLD",
    "GRID_TOL_VOXELS",
    "binarize_brain_mask",
    "check_same_grid",
    "grid_offset_voxels",
]

#: A voxel is brain where the given mask's value is strictly above this.
BRAIN_THRESHOLD = 0.5

#: Largest distance, in voxels (along each voxel axis), between a voxel centre placed by
#: the mask's affine and by the image's: 1 % of a voxel is far above the float32
#: round-off of a NIfTI header and far below anything visible in a mask.
GRID_TOL_VOXELS = 0.01


def _format_affine(affine: np.ndarray) -> str:
    rows = np.asarray(affine, dtype=np.float64)[:3]
    return "[" + "; ".join(" ".join(f"{v:.6g}" for v in row) for row in rows) + "]"


def grid_offset_voxels(shape: tuple[int, ...], affine_a: np.ndarray, affine_b: np.ndarray) -> float:
    """Largest shift, in voxels of grid ``b``, of a voxel centre of grid ``a`` (shape ``shape``).

    The index ``i`` of grid ``a`` sits at index ``inv(B) A i`` of grid ``b``;
    the result is ``max |inv(B) A i - i|`` over the grid's corners and axes
    (the map is affine, so the corners bound every voxel). 0 for equal affines.
    """
    a = np.asarray(affine_a, dtype=np.float64)
    b = np.asarray(affine_b, dtype=np.float64)
    t = np.linalg.solve(b, a)
    hi = np.asarray(shape[:3], dtype=np.float64) - 1.0
    corners = np.array(
        [[x, y, z, 1.0] for x in (0.0, hi[0]) for y in (0.0, hi[1]) for z in (0.0, hi[2])]
    )
    moved = corners @ t.T
    return float(np.max(np.abs(moved[:, :3] - corners[:, :3])))


def check_same_grid(
    mask_shape: tuple[int, ...],
    mask_affine: np.ndarray,
    image_shape: tuple[int, ...],
    image_affine: np.ndarray,
) -> None:
    """Refuse a mask that is not on the image's voxel grid.

    Raises
    ------
    InputError
        Naming both shapes, or both affines and the largest voxel offset
        (the caller names the mask file).
    """
    ms, im = tuple(int(s) for s in mask_shape), tuple(int(s) for s in image_shape)
    if ms != im:
        raise InputError(
            f"shape {ms} differs from the image's {im}: the mask must be on the image's "
            "voxel grid (nothing is resampled)"
        )
    a = np.asarray(mask_affine, dtype=np.float64)
    b = np.asarray(image_affine, dtype=np.float64)
    if not (np.all(np.isfinite(a)) and abs(np.linalg.det(a[:3, :3])) > 0):
        raise InputError(f"affine {_format_affine(a)} is singular or not finite")
    offset = grid_offset_voxels(ms, a, b)
    if not offset <= GRID_TOL_VOXELS:
        raise InputError(
            f"affine {_format_affine(a)} differs from the image's "
            f"{_format_affine(b)} (voxel centres up to {offset:.3g} voxels apart, more than "
            f"{GRID_TOL_VOXELS:g}): the mask must be on the image's voxel grid"
        )


def binarize_brain_mask(values: np.ndarray, image: np.ndarray) -> np.ndarray:
    """The brain (values ``> 0.5``) of a given mask, checked against its image.

    Parameters
    ----------
    values : ndarray of numbers
        The mask's voxel values, on the image's grid and in its axis order.
    image : ndarray of numbers, same shape
        The image (finite; checked by its reader).

    Returns
    -------
    ndarray of bool
        ``values > 0.5``.

    Raises
    ------
    InputError
        Another shape, non-numeric or non-finite values, an empty mask, or
        no brain voxel on the image's non-background (the caller adds the
        file).
    """
    v = np.asarray(values)
    img = np.asarray(image)
    if v.dtype.kind not in "biuf":
        raise InputError(f"the values must be numbers, got dtype {v.dtype}")
    if v.shape != img.shape:
        raise InputError(f"shape {v.shape} differs from the image's {img.shape}")
    problem = non_finite_problem(v)
    if problem:
        raise InputError(problem)
    brain = v > BRAIN_THRESHOLD
    if not brain.any():
        top = v.max() if v.size else 0
        raise InputError(
            f"empty: no voxel is above {BRAIN_THRESHOLD:g} (largest value "
            f"{float(top):.6g}; brain = voxels > {BRAIN_THRESHOLD:g})"
        )
    tissue = img > threshold_otsu(img)
    if not np.any(brain & tissue):
        raise InputError(
            f"no overlap with the image: none of its {int(brain.sum())} brain voxels is on "
            "the image's non-background (above its Otsu threshold); is it the mask of another "
            "image, or misplaced?"
        )
    return brain
