"""Preprocessing of a stack of MR slices (specification section 1).

Per 8-bit slice ``I`` (Arakeri & Reddy 2013, section 3.1):

1. ``I1`` = 3x3 median filter of ``I``;
2. ``I2`` = clip(``I1`` (*) h, 0, 255) with ``h`` MATLAB's
   ``fspecial('unsharp', alpha)`` kernel [A1];
3. ``I3`` = histogram equalisation of ``I2`` with 256 levels [A2];
4. ``M_brain`` = skull removal on the *original* ``I``: Otsu threshold,
   opening with a disk, largest 8-connected component, dilation with the same
   disk, hole filling [A3]; ``J = I3 * M_brain``.

Steps 2 and 3 are implemented but **off by default** (``sharpen=False``,
``equalize=False``) and off in ``configs/paper.yaml`` too: equalisation
flattens the very histogram whose modes section 2 counts, and the unsharp
kernel's overshoot saturates at the gray of CSF and turns noise and tissue
edges into extra modes. :func:`preprocess_volume` gives the measurements
behind this choice (and ``reports/PAPER.md``, ``make paper``, the figures of
every reading tried).

The volume is processed as a stack: the median filter and the unsharp
kernel are applied to the whole ``(z, y, x)`` array with a kernel of depth 1
(so slices never mix), the equalisation is one table look-up per slice, the
morphology (erosion, labelling, dilation, hole filling) runs on the whole
stack with in-plane structuring elements, and only the skull removal's Otsu
thresholds are computed slice by slice.

The package holds the steps by concept: :mod:`~tumor3d.imaging.preprocess.intensity`
(8-bit window, masked background), :mod:`~tumor3d.imaging.preprocess.filters` (steps
1-3), :mod:`~tumor3d.imaging.preprocess.skull` (step 4),
:mod:`~tumor3d.imaging.preprocess.masks` (in-plane mask morphology, the foreground
brain), :mod:`~tumor3d.imaging.preprocess.notes` (plausibility notes on the brain mask)
and :mod:`~tumor3d.imaging.preprocess.volume` (:func:`preprocess_volume`). The public
names are importable from here.
"""

from __future__ import annotations

from tumor3d.imaging.preprocess.filters import equalize_slices, unsharp_kernel
from tumor3d.imaging.preprocess.intensity import (
    BACKGROUND_RANGE_QUANTILES,
    BACKGROUND_TOLERANCE,
    MaskedBackground,
    masked_background,
    to_uint8,
)
from tumor3d.imaging.preprocess.masks import fill_holes_per_slice, foreground_brain_mask, true_box
from tumor3d.imaging.preprocess.notes import (
    MAX_BRAIN_HEIGHT_MM,
    MAX_INTRACRANIAL_ML,
    MAX_OUTLINE_SHIFT_STEPS,
    MIN_BRAIN_SLICE_MM2,
    MIN_BRAIN_SLICE_SHARE,
    brain_coverage_note,
    brain_height_note,
    brain_mask_figures,
    brain_mask_notes,
    brain_size_note,
    brain_volume_note,
    outline_shift_mm,
    slice_step_note,
    tissue_slice_count,
)
from tumor3d.imaging.preprocess.skull import SKULL_THRESHOLDS, remove_skull
from tumor3d.imaging.preprocess.volume import BRAIN_EXTRACTIONS, PreprocessResult, preprocess_volume

__all__ = [
    "BACKGROUND_RANGE_QUANTILES",
    "BACKGROUND_TOLERANCE",
    "BRAIN_EXTRACTIONS",
    "MAX_BRAIN_HEIGHT_MM",
    "MAX_INTRACRANIAL_ML",
    "MAX_OUTLINE_SHIFT_STEPS",
    "MIN_BRAIN_SLICE_MM2",
    "MIN_BRAIN_SLICE_SHARE",
    "SKULL_THRESHOLDS",
    "MaskedBackground",
    "PreprocessResult",
    "brain_coverage_note",
    "brain_height_note",
    "brain_mask_figures",
    "brain_mask_notes",
    "brain_size_note",
    "brain_volume_note",
    "equalize_slices",
    "fill_holes_per_slice",
    "foreground_brain_mask",
    "masked_background",
    "outline_shift_mm",
    "preprocess_volume",
    "remove_skull",
    "slice_step_note",
    "tissue_slice_count",
    "to_uint8",
    "true_box",
    "unsharp_kernel",
]
