"""A tumour segmentation given by the user instead of the one the segment stage computes.

The rules (pure: arrays in, arrays out; reading the file is
:mod:`tumor3d.storage.given_segmentation`'s):

* **Grid.** The mask lies on the image's voxel grid, checked as a given
  brain mask is (:func:`tumor3d.imaging.brain_mask.check_same_grid`: the same shape,
  voxel centres within 0.01 voxel). Nothing is resampled.
* **Tumour** = voxels whose value is ``> 0.5`` (:data:`TUMOUR_THRESHOLD`),
  so a 0/1 label, a 0/255 mask and a probability map all work. A multi-label
  segmentation (BraTS labels 1, 2, 4) counts every label as tumour.
* **Refused:** non-numeric or non-finite values. An empty mask is a valid
  answer (no tumour): the run reports none.
* **Kept as given:** neither the brain mask nor the abnormal-slice detection
  trims it; the detection still runs (its table is reported) and Eq. 7 sums
  every slice holding tumour (rule ``segmented``). The caveat of a tumour on
  the scan's first or last slice is said as for any method.
"""

from __future__ import annotations

import numpy as np

from tumor3d.errors import InputError
from tumor3d.segmentation.caveats import segmentation_caveats
from tumor3d.segmentation.segment import SegmentationResult

__all__ = [
    "GIVEN_METHOD",
    "TUMOUR_THRESHOLD",
    "binarize_segmentation",
    "given_definition",
    "given_segmentation",
]

#: ``segment_method`` of a run whose tumour mask the user gave.
GIVEN_METHOD = "given"

#: A voxel is tumour where the given segmentation's value is strictly above this.
TUMOUR_THRESHOLD = 0.5


def given_definition(name: str | None = None) -> str:
    """What a given segmentation's mask (every volume) holds, in words (``measured``).

    >>> given_definition("seg.nii.gz")
    'the segmentation given by the user (seg.nii.gz)'
    """
    return "the segmentation given by the user" + (f" ({name})" if name else "")


def binarize_segmentation(values: np.ndarray) -> np.ndarray:
    """The tumour (values ``> 0.5``) of a given segmentation.

    Raises
    ------
    InputError
        A non-3-D array, non-numeric or non-finite values (the caller adds
        the file).
    """
    arr = np.asarray(values)
    if arr.ndim != 3:
        raise InputError(f"the segmentation must be 3-D, got shape {arr.shape}")
    if arr.dtype == bool:
        return arr.copy()
    if not (np.issubdtype(arr.dtype, np.integer) or np.issubdtype(arr.dtype, np.floating)):
        raise InputError(f"the segmentation's values must be numbers, got {arr.dtype}")
    if np.issubdtype(arr.dtype, np.floating) and not np.all(np.isfinite(arr)):
        n = int(np.count_nonzero(~np.isfinite(arr)))
        raise InputError(f"the segmentation holds {n} NaN or infinite value(s)")
    return arr > TUMOUR_THRESHOLD


def given_segmentation(
    tumor_mask: np.ndarray, *, spacing_mm: tuple[float, float, float] | None = None
) -> SegmentationResult:
    """The segment stage's result for a mask the user gave, on the scan's ``(z, y, x)`` grid.

    ``tumor_pixels`` (Eq. 8's ``N_i``) counts the mask per slice, ``selection``
    is ``"given"`` on every slice holding tumour, and the caveats are those
    of the mask's extent (:func:`tumor3d.segmentation.caveats.segmentation_caveats`
    without a symmetry plane or a head exterior: those judge a method's
    mask, not the user's).
    """
    tumor = np.asarray(tumor_mask, dtype=bool)
    if tumor.ndim != 3:
        raise InputError(f"the segmentation must be 3-D (z, y, x), got shape {tumor.shape}")
    nz = tumor.shape[0]
    pixels = tumor.sum(axis=(1, 2)).astype(np.int64)
    return SegmentationResult(
        tumor_mask=tumor,
        tumor_pixels=pixels,
        reference_centers=np.full(3, np.nan),
        tumor_center_gray=np.full(nz, np.nan),
        selection=np.where(pixels > 0, GIVEN_METHOD, "").astype(str),
        caveats=segmentation_caveats(tumor, spacing_mm=spacing_mm),
        method=GIVEN_METHOD,
    )
