"""Plausibility notes on a brain mask and its scan, and on the header's slice step.

The mask's volume, cross-sections and slice coverage; the slice step against the
head's own shape.

Each note is None when the mask is plausible, else a sentence for the
report saying what is wrong and why it matters.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

#: No brain mask can hold more than this (mL): the intracranial volume of adults
#: (brain, CSF and meninges together) lies between about 1.1 and 1.9 L. A larger
#: mask holds scalp, face or neck (measured: 2.6-3.3 L on the raw clinical heads of
#: ``../shared/data``, where the per-slice skull removal keeps the scalp).
MAX_INTRACRANIAL_ML = 2000.0


#: What a doubtful brain mask means for a tumour segmented inside it, and for one read
#: from the whole head (the learned method: ``SegmentMethod.within_brain_mask`` False).
_CONSEQUENCE = {
    True: "the result (a tumour volume, or no tumour found) is not reliable",
    False: (
        "the brain surface and the brain's contour in overlay_brain.png are off; the tumour, "
        "read from the whole head, is not confined to this mask (check overlay_tumor.png)"
    ),
}


def brain_volume_note(brain_volume_ml: float, *, doubts_result: bool = True) -> str | None:
    """A warning for a brain mask that holds more than any skull can, else None.

    Such a mask holds scalp, face or neck, where the lesion model may find a
    "lesion" (fat, muscle, sinus), and its statistics of normal tissue are off; the
    result, a tumour volume or "no tumour found", is then not to be trusted when
    the tumour was segmented inside the mask (``doubts_result``); a method that
    reads the whole head is told what the mask still spoils.

    >>> brain_volume_note(1400.0) is None
    True
    >>> brain_volume_note(3257.0)[:40]
    'brain mask of 3257 mL: more than any sku'
    >>> "not reliable" in brain_volume_note(3257.0, doubts_result=False)
    False
    """
    v = float(brain_volume_ml)
    if not v > MAX_INTRACRANIAL_ML:
        return None
    return (
        f"brain mask of {v:.0f} mL: more than any skull holds ({MAX_INTRACRANIAL_ML:.0f} mL), "
        f"so it holds scalp or face and {_CONSEQUENCE[bool(doubts_result)]}: give the brain "
        "mask (--brain-mask) or set preprocess.brain_extraction: head, and check "
        "overlay_brain.png"
    )


#: No whole human brain shows less than this (mm2) on its largest slice: a brain's
#: largest cross-section (axial, coronal or sagittal) is about 60 cm2 at birth and
#: 100-250 cm2 in adults (measured: 142-258 cm2 on the real volumes and phantoms the
#: project uses). Below a third of the newborn's, the voxel size in the header is off
#: (a unit error: 0.1 mm read for 1 mm pixels makes the area 100 times smaller) or
#: the brain was lost.
MIN_BRAIN_SLICE_MM2 = 2000.0


def brain_size_note(largest_slice_mm2: float) -> str | None:
    """A warning for a brain mask too small to be a human brain, else None.

    ``largest_slice_mm2`` is the brain mask's area on its largest slice
    (through the scan's pixel spacing): see :data:`MIN_BRAIN_SLICE_MM2`.

    >>> brain_size_note(15000.0) is None
    True
    >>> brain_size_note(150.0)[:44]
    'brain mask of at most 1.5 cm2 on any slice: '
    """
    a = float(largest_slice_mm2)
    if not a < MIN_BRAIN_SLICE_MM2:
        return None
    return (
        f"brain mask of at most {a / 100.0:.1f} cm2 on any slice: no human brain is that small "
        f"(its largest cross-section is about 60 cm2 at birth, 100-250 cm2 in adults), so the "
        "voxel size in the image header is likely wrong (a unit error, e.g. 0.1 mm pixels "
        "for 1 mm) or the brain was lost, and every volume is not reliable: check the "
        "header's voxel size and overlay_brain.png"
    )


#: No brain mask spans more than this (mm) along the slices when the header's slice step
#: is the true one: an adult brain is 130-180 mm in any direction and a whole head about
#: 230 mm from vertex to chin (measured: at most 150 mm on the 96 real cross-validation
#: volumes, 145 mm on the BraTS brains cut to 5 mm slabs, 150 mm on a raw 6.5 mm T1c head
#: whose mask holds its scalp). Above it the slices lie closer together than the header
#: says: a 10 mm step written for 5 mm doubled every volume with status ok before this
#: note (a user audit).
MAX_BRAIN_HEIGHT_MM = 250.0


def brain_height_note(brain_slices: int, slice_step_mm: float) -> str | None:
    """A warning for a brain mask taller than any head along the slices, else None.

    ``brain_slices`` slices with brain, ``slice_step_mm`` apart (the header's step):
    see :data:`MAX_BRAIN_HEIGHT_MM`.

    >>> brain_height_note(28, 5.0) is None
    True
    >>> brain_height_note(28, 10.0)[:48]
    'brain mask on 28 slices of 10 mm: 280 mm tall, w'
    """
    n, step = int(brain_slices), float(slice_step_mm)
    height = n * step
    if not height > MAX_BRAIN_HEIGHT_MM:
        return None
    return (
        f"brain mask on {n} slices of {step:g} mm: {height:.0f} mm tall, where no head is "
        f"taller than about {MAX_BRAIN_HEIGHT_MM:.0f} mm: the slice step in the header is "
        "likely too large, and every volume in mm3 and mL scales with it: check the "
        "header's voxel size"
    )


#: A brain mask on fewer than this share of the slices that hold tissue has lost most
#: of the brain: the brain spans most of a head scan's slices (the phantoms' whole
#: heads: 63-73 %, 59 % with ``brain_extraction: head``; the raw clinical heads of
#: ``../shared/data``: 65-100 %; skull-stripped volumes: 100 %), while a skull removal
#: misled by a face or neck slice kept 3 of 26.
MIN_BRAIN_SLICE_SHARE = 0.5


def tissue_slice_count(original_u8: np.ndarray) -> int:
    """Slices of a ``(z, y, x)`` stack that hold anything: not one constant gray.

    A skull-stripped volume's slices beyond the brain are its constant background;
    a raw head's slices hold head, or at least the scanner's noise.

    >>> tissue_slice_count(np.stack([np.zeros((4, 4)), np.eye(4)]).astype(np.uint8))
    1
    """
    flat = np.asarray(original_u8).reshape(len(original_u8), -1)
    if flat.size == 0:
        return 0
    return int(np.count_nonzero(flat.max(axis=1) > flat.min(axis=1)))


def brain_coverage_note(
    brain_slices: int, tissue_slices: int, brain_extraction: str = "", *, doubts_result: bool = True
) -> str | None:
    """A warning for a brain mask on too few of the slices that hold tissue, else None.

    Below :data:`MIN_BRAIN_SLICE_SHARE`, the skull removal has most likely lost
    the brain (a face or neck slice taken for the brain's widest, or the scalp
    joined to the brain on a slice), and what it kept may be face or neck.
    ``brain_extraction`` (the mode used) keeps the advice from naming the mode
    that failed; ``doubts_result`` as :func:`brain_volume_note`.

    >>> brain_coverage_note(20, 30) is None
    True
    >>> brain_coverage_note(3, 26)[:48]
    'brain mask on 3 of the 26 slices that hold tissu'
    """
    b, t = int(brain_slices), int(tissue_slices)
    if t <= 0 or b >= MIN_BRAIN_SLICE_SHARE * t:
        return None
    advice = "give the brain mask (--brain-mask)"
    if brain_extraction != "head":
        advice += " or set preprocess.brain_extraction: head"
    return (
        f"brain mask on {b} of the {t} slices that hold tissue: the skull removal has likely "
        f"lost most of the brain (or kept face or neck), so {_CONSEQUENCE[bool(doubts_result)]}: "
        f"{advice}, and check overlay_brain.png"
    )


def brain_mask_figures(
    brain: np.ndarray,
    spacing_mm: tuple[float, float, float],
    brain_extraction: str,
    original_u8: np.ndarray,
) -> dict[str, Any]:
    """The figures of a ``(z, y, x)`` brain mask and its scan for :func:`brain_mask_notes`.

    ``brain_voxels``, ``brain_volume_ml``, ``brain_slices`` (slices it covers),
    ``brain_max_slice_mm2`` (its largest slice), with ``brain_extraction`` (the
    mode used, or ``"given"``), and of the scan's 8-bit ``original_u8``:
    ``tissue_slices`` (:func:`tissue_slice_count`), ``outline_shift_mm``
    (:func:`outline_shift_mm`, None when it cannot be measured) and ``slice_step_mm``:
    the preprocess stage's values.

    >>> f = brain_mask_figures(np.ones((2, 10, 10), bool), (5.0, 1.0, 1.0), "foreground",
    ...                        np.full((2, 10, 10), 9, np.uint8))
    >>> f["brain_volume_ml"], f["brain_slices"], f["brain_max_slice_mm2"], f["tissue_slices"]
    (1.0, 2, 100.0, 0)
    """
    voxels = int(np.count_nonzero(brain))
    per_slice = np.count_nonzero(brain, axis=(1, 2))
    shift = outline_shift_mm(original_u8, spacing_mm)
    return {
        "brain_voxels": voxels,
        "brain_volume_ml": voxels * float(np.prod(spacing_mm)) / 1000.0,
        "brain_extraction": str(brain_extraction),
        "brain_slices": int(np.count_nonzero(per_slice)),
        "brain_max_slice_mm2": float(per_slice.max()) * float(spacing_mm[1]) * float(spacing_mm[2]),
        "tissue_slices": tissue_slice_count(original_u8),
        "outline_shift_mm": None if shift is None else round(shift, 3),
        "slice_step_mm": float(spacing_mm[0]),
    }


def brain_mask_notes(
    figures: Mapping[str, Any], *, doubts_result: bool = True
) -> tuple[list[str], list[str]]:
    """The notes on a brain mask from its :func:`brain_mask_figures`, in two lists.

    Those on the skull removal (:func:`brain_volume_note`, :func:`brain_coverage_note`)
    and those on the voxel size (:func:`brain_size_note`, :func:`slice_step_note`,
    :func:`brain_height_note`). The
    first doubt a tumour segmented inside the mask (``doubts_result`` False words them
    for a method that reads the whole head); the second doubt every volume. No coverage
    note for a given mask (the user's) nor without the slice counts, no size note
    without the largest slice, no slice-step note without the outline's shift (figures
    stored before they were, or a stack with no verdict: ``outline_shift_mm`` None).

    >>> brain_mask_notes({"brain_volume_ml": 1400.0})
    ([], [])
    >>> skull, size = brain_mask_notes({"brain_volume_ml": 3257.0, "brain_max_slice_mm2": 150.0})
    >>> [n[:22] for n in skull], [n[:22] for n in size]
    (['brain mask of 3257 mL:'], ['brain mask of at most '])
    """
    skull = [brain_volume_note(figures.get("brain_volume_ml", 0.0), doubts_result=doubts_result)]
    if figures.get("brain_extraction") != "given":
        slices = (figures.get("brain_slices", 0), figures.get("tissue_slices", 0))
        skull.append(
            brain_coverage_note(
                *slices, figures.get("brain_extraction", ""), doubts_result=doubts_result
            )
        )
    size = []
    if "brain_max_slice_mm2" in figures:  # a mask of the user's too: theirs may be off
        size.append(brain_size_note(figures["brain_max_slice_mm2"]))
    if figures.get("outline_shift_mm") is not None and figures.get("slice_step_mm"):
        size.append(slice_step_note(figures["outline_shift_mm"], figures["slice_step_mm"]))
    if figures.get("brain_slices") and figures.get("slice_step_mm"):
        size.append(brain_height_note(figures["brain_slices"], figures["slice_step_mm"]))
    return [n for n in skull if n], [n for n in size if n]


#: The head's outline moves between neighbouring slices by at most about this many slice
#: steps when the header's slice step is the true one: measured on its circle-equivalent
#: radius, the median change over the slices where the head is at least a quarter of its
#: largest cross-section is the slope of the head's surface, about half a step for a ball
#: and for a head. Measured with the true step (``benchmarks/slice_step_survey.py``):
#: 0.4-0.7 on BraTS volumes at 1 mm and cut to 5 mm slices (0.9 at most resliced coronal
#: or sagittal at 1 mm), 0.1-0.5 on the native clinical scans of ``../shared/data``
#: (5.5-6.5 mm, raw heads and a coronal 3 mm head), 0.5-0.6 on the phantoms; 0.9-5.5 on
#: the 45 clinical LGG heads, exported without their voxel size and written as a nominal
#: 1 mm (43 of them above this limit, one without verdict). The shape of the outline is
#: left out: a skull-stripped brain's sulci changed it by 5 steps from one 1 mm slice to
#: the next. The margin is thin on both sides (reports/learned_cv.md).
MAX_OUTLINE_SHIFT_STEPS = 1.0


#: At most this share of the slices' border voxels non-zero: a masked volume (skull-stripped),
#: whose head :func:`outline_shift_mm` reads as its non-zero support. Every BraTS volume has
#: none non-zero; the clinical LGG heads' noisy air leaves 0.8-100 % of their borders
#: non-zero in 8 bits (2 of the 45 none: their support is then the head).
MASKED_BORDER_SHARE = 0.001


def outline_shift_mm(
    original_u8: np.ndarray, spacing_mm: tuple[float, float, float]
) -> float | None:
    """How far the head's outline moves from one slice to the next, in mm (the median).

    ``original_u8`` is the scan's 8-bit ``(z, y, x)`` stack, slices on axis 0;
    ``spacing_mm`` is ``(slice step, row, column)``.
    The head is the stack's voxels above half the Otsu threshold of its non-zero ones;
    in a masked volume (a skull-stripped brain: every voxel on the slices' borders is 0)
    it is every non-zero voxel, since there half the Otsu level drops dark tissue at the
    brain's edge by a different amount on each slice (the algoseg T2 cut to 2 mm slabs
    every 5 mm moved 1.005 steps by the threshold, 0.79 by its support). Opened and
    hole-filled slice by slice; its outline's
    move between neighbouring slices is the change of its circle-equivalent radius
    ``sqrt(area / pi)``. The median over the neighbouring slices whose head covers at
    least a quarter of the largest cross-section; None with fewer than 3 such pairs, or
    when the largest cross-section is on the first or last slice: a stack of one end of
    the head holds only its steep part (the top 40 mm of a 1 mm brain moved 1.1 steps).

    >>> yy, xx = np.mgrid[:64, :64]
    >>> radii = [20, 22, 24, 25, 24, 22, 20]  # a head's cross-sections, 1 px = 1 mm
    >>> head = np.stack([((yy - 32) ** 2 + (xx - 32) ** 2 < r * r) * 200 for r in radii])
    >>> round(outline_shift_mm(head.astype(np.uint8), (5.0, 1.0, 1.0)), 1)  # steps 2 2 1 1 2 2
    2.0
    """
    from scipy import ndimage as ndi
    from skimage.filters import threshold_otsu

    from tumor3d.imaging.preprocess.masks import _IN_PLANE_4, fill_holes_per_slice

    u = np.asarray(original_u8)
    if u.ndim != 3 or len(u) < 4 or not (u > 0).any():
        return None
    border = np.concatenate([u[:, [0, -1], :].ravel(), u[:, :, [0, -1]].ravel()])
    if np.count_nonzero(border) <= MASKED_BORDER_SHARE * border.size:  # masked: its support
        level = 0.0
    else:
        values = u[u > 0]
        threshold = threshold_otsu(values) if values.min() < values.max() else values.min()
        level = max(0.5 * float(threshold), 1.0)
    head = ndi.binary_opening(u > level, _IN_PLANE_4, iterations=2)
    head = fill_holes_per_slice(head)
    area = np.count_nonzero(head, axis=(1, 2)) * float(spacing_mm[1]) * float(spacing_mm[2])
    if area.max() <= 0 or int(np.argmax(area)) in (0, len(area) - 1):
        return None  # nothing, or not through the widest part: a slab off its middle
    big = area >= 0.25 * area.max()
    pairs = np.flatnonzero(big[:-1] & big[1:])
    if len(pairs) < 3:
        return None
    radius = np.sqrt(area / np.pi)
    return float(np.median(np.abs(radius[pairs + 1] - radius[pairs])))


def slice_step_note(shift_mm: float, slice_step_mm: float) -> str | None:
    """A warning for a slice step the head's own shape contradicts, else None.

    ``shift_mm`` (:func:`outline_shift_mm`) above :data:`MAX_OUTLINE_SHIFT_STEPS`
    slice steps: the slices lie farther apart than the header says (or the pixels are
    smaller), as in images exported without their voxel size and written as 1 mm;
    every volume scales with the step.

    >>> slice_step_note(2.5, 5.0) is None
    True
    >>> slice_step_note(2.8, 1.0)[:45]
    "the head's outline moves 2.8 mm from slice to"
    """
    shift, step = float(shift_mm), float(slice_step_mm)
    if not (step > 0 and shift > MAX_OUTLINE_SHIFT_STEPS * step):
        return None
    return (
        f"the head's outline moves {shift:.1f} mm from slice to slice, {shift / step:.1f} "
        f"times the slice step in the header ({step:g} mm), where a head's outline moves "
        f"about half a step and at most {MAX_OUTLINE_SHIFT_STEPS:g} step: the slice step "
        "(or the pixel size) in the header is likely wrong (images exported without their "
        "voxel size are often written as 1 mm), and every volume in mm3 and mL scales "
        "with it: check the header's voxel size"
    )
