"""Steps 2 and 3 to 3f: the seeds, their components, and which of them is a lesion.

Seeds outside the normal model (step 2), their significant components
(step 3), the depth rule (3b), the mirror test (3c), the deep crossing of
the midline (3d), the normal tail (3e) and the lesion straddling the
midline (3f); see :mod:`tumor3d.segmentation.lesion`.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from tumor3d.errors import InputError
from tumor3d.segmentation.lesion.normal import NormalModel, _beyond_normal_tail, _passing_ids
from tumor3d.segmentation.lesion.pixels import _blur_reach
from tumor3d.segmentation.lesion.regions import (
    _box_dilate,
    _significant_components,
    _touching,
    _within_mm,
)
from tumor3d.segmentation.lesion.symmetry import (
    SYMMETRIC_REGAIN_MM,
    SYMMETRY_TOLERANCE_MM,
    MirrorPlane,
    _asymmetric_seeds,
    _mirrored,
)

#: Step 3b: the grid spacing (mm) on which the brain's depth is computed (see _depth_mm).
DEPTH_GRID_MM = 2.0


#: Step 3b: the depth percentile of a candidate that must reach the brain's median
#: depth (its deepest tenth; a robust maximum, see the package docstring).
DEPTH_PERCENTILE = 90.0


#: Step 3f (FLAIR): when no asymmetric lesion is kept, look for one straddling the
#: mid-sagittal plane (see _midline_lesion and the package docstring).
MIDLINE_LESIONS = True


#: Step 3c: asymmetric candidates examined, largest first.
MAX_CANDIDATES = 8


def _depth_mm(brain: np.ndarray, spacing_mm: tuple[float, ...]) -> np.ndarray:
    """3-D distance (mm) of each brain voxel to the outside of the brain mask.

    Computed on a subgrid of about :data:`DEPTH_GRID_MM` spacing (every
    ``k``-th voxel along an axis finer than that) and read back by nearest
    neighbour: step 3b compares two depth percentiles of a brain some 70 mm
    deep, which a 2 mm grid resolves, at an eighth of the cost on 1 mm voxels.
    """
    if any(not (np.isfinite(v) and v > 0) for v in spacing_mm):
        raise InputError(f"spacing_mm must be three positive numbers, got {spacing_mm}")
    step = [max(1, int(DEPTH_GRID_MM // float(v))) for v in spacing_mm]
    coarse = brain[:: step[0], :: step[1], :: step[2]]
    # the brain touching the volume's edge continues beyond it: no distance there
    grid_mm = [float(v) * k for v, k in zip(spacing_mm, step, strict=True)]
    d = ndi.distance_transform_edt(coarse, sampling=grid_mm)
    for axis, k in enumerate(step):
        if k > 1:
            d = np.repeat(d, k, axis=axis)
    d = d[: brain.shape[0], : brain.shape[1], : brain.shape[2]]
    return np.where(brain, d, 0.0)


def _inner_half(
    brain: np.ndarray, depth: np.ndarray, spacing_mm: tuple[float, ...], lr_axis: int
) -> np.ndarray:
    """Step 3d: the brain voxels at least as deep as the brain's median depth.

    ``depth`` is :func:`_depth_mm` of ``brain``. Its grid is anchored at the
    array's first voxel, which a left-right flip moves; averaged with the
    depth of the brain flipped along ``lr_axis`` (and flipped back), the
    voxel-wise decision has no preferred side: a mirrored image gives the
    mirrored lesion.
    """
    flipped = np.flip(_depth_mm(np.flip(brain, lr_axis), spacing_mm), lr_axis)
    sym = 0.5 * (depth + flipped)
    return brain & (sym >= float(np.median(sym[brain])))


def _deep_components(
    labels: np.ndarray,
    ids: np.ndarray,
    brain: np.ndarray,
    spacing_mm: tuple[float, ...],
    depth: np.ndarray | None = None,
) -> np.ndarray:
    """Step 3b: the ids (order kept) of the components that reach the inner half.

    Inner half of the brain = deeper than the brain's median depth; a
    component passes when its :data:`DEPTH_PERCENTILE` th depth percentile
    reaches that depth.
    """
    if depth is None:
        depth = _depth_mm(brain, spacing_mm)
    brain_median = float(np.median(depth[brain]))
    keep = [i for i in ids if np.percentile(depth[labels == i], DEPTH_PERCENTILE) >= brain_median]
    return np.asarray(keep, dtype=ids.dtype)


def _candidates(
    model,
    sm,
    img,
    b,
    smoothing_px,
    min_region_pixels,
    min_slices,
    keep_largest,
    spacing_mm,
    plane,
    voxel_mm,
    crossing=False,
    contrast=False,
):
    """Steps 2, 3, 3b, 3c, 3d and 3f (with ``crossing``), 3e (with ``contrast``) and 6.

    Returns ``(not-CSF mask, labels, significant kept ids, satellites,
    across, midline)``; ``midline`` tells that step 3f found the lesion.
    ``satellites`` holds the significant seed components that were not kept
    (with ``keep_largest``; None otherwise or when nothing was kept); with a
    mirror plane each has the mirrored seeds within
    ``SYMMETRIC_REGAIN_MM`` of it, as the kept core has them. Step 4b joins
    those the refined lesion reaches. ``across`` (step 3d, with ``crossing``
    and a mirror plane and the depth of step 3b; None otherwise) holds the
    seeds in the inner half of the brain connected to the kept lesion
    through such seeds, beyond the lesion's own extent (its labels), other
    than significant asymmetric components (those are satellites).
    """
    not_csf = img < model.csf_threshold
    if plane is not None and not not_csf.all():
        # CSF is bilateral (ventricles, sulci, cisterns); fluid-bright voxels without a
        # fluid-bright mirror are a cyst or necrosis of the lesion, not CSF
        csf = b & ~not_csf
        not_csf = ~_mirrored(csf, plane, voxel_mm) | ~csf
    seeds = b & (sm > model.seed_threshold) & not_csf
    if not not_csf.all():
        # the smoothed seeds within the blur's reach (2 sigma) of CSF owe their
        # brightness to the CSF (partial volume, blur): no seeds
        reach = _blur_reach(smoothing_px)
        halo = _box_dilate(~not_csf & b, reach, reach)
        seeds &= ~halo
    full_seeds = seeds
    across = None
    midline = False  # step 3f found the lesion
    if plane is not None and seeds.any():
        seeds = _asymmetric_seeds(seeds, plane, voxel_mm)
    labels, ids = _significant_components(seeds, min_region_pixels, min_slices)
    significant = ids
    if ids.size and plane is None:
        if spacing_mm is not None:
            ids = _deep_components(labels, ids, b, spacing_mm)
        if contrast:
            ids = _passing_ids(labels, ids, sm, model)
        satellites = np.isin(labels, np.setdiff1d(significant, ids[:1])) if keep_largest else None
    elif ids.size or (plane is not None and crossing and MIDLINE_LESIONS):
        # the asymmetric seeds decide whether (and where) there is a lesion; the lesion
        # is the seed component holding that core, with the mirrored seeds within
        # SYMMETRIC_REGAIN_MM of it (a tumour's part near the midline or next to a
        # bilateral structure); the depth rule (3b) judges that whole lesion
        depth = None if spacing_mm is None else _depth_mm(b, spacing_mm)
        out = np.zeros(labels.shape, dtype=np.int64)
        n_out = 0
        for i in ids[:MAX_CANDIDATES]:
            core0 = labels == i
            if out[core0].any():
                continue  # already part of a kept lesion
            near = _within_mm(core0, SYMMETRIC_REGAIN_MM, voxel_mm)
            comp = _touching(full_seeds & (seeds | near), core0)
            if not _passes_evidence(comp, b, spacing_mm, depth, sm, model, contrast):
                continue
            n_out += 1
            out[comp & (out == 0)] = n_out
            if keep_largest:
                break
        if crossing and not n_out and depth is not None and MIDLINE_LESIONS:
            # step 3f: no asymmetric lesion; one straddling the mid-sagittal plane is
            # invisible to step 3c (its mirror image is itself)
            comp = _midline_lesion(
                full_seeds, plane, voxel_mm, min_region_pixels, min_slices, b, spacing_mm,
                depth, sm, model, contrast,
            )  # fmt: skip
            if comp is not None:
                n_out = 1
                out[comp] = 1
                midline = True
        if crossing and n_out and depth is not None:
            # step 3d: the seeds of the inner half of the brain connected to the lesion
            # through such seeds, mirrored or not (a tumour crossing the midline)
            kept = out > 0
            deep = _inner_half(b, depth, spacing_mm, plane.axis)
            across = _touching(kept | (full_seeds & deep), kept) & ~kept
            # an asymmetric component reached this way is a satellite (step 4b: refined
            # with the rings, as any lesion of its own), not mirrored tissue
            across &= ~np.isin(labels, significant)
        satellites = None
        if keep_largest and n_out:
            # every other significant asymmetric component, with its mirrored seeds near
            # it as the kept core has them (no depth test: it may join a deep lesion)
            free = out == 0 if across is None else (out == 0) & ~across
            sat0 = np.isin(labels, significant) & free
            if sat0.any():
                near = _within_mm(sat0, SYMMETRIC_REGAIN_MM, voxel_mm)
                satellites = _touching(full_seeds & (seeds | near), sat0) & free
        labels, ids = out, np.arange(1, n_out + 1)
    else:
        satellites = None
    return not_csf, labels, ids, satellites, across, midline


def _passes_evidence(
    comp: np.ndarray,
    b: np.ndarray,
    spacing_mm: tuple[float, ...] | None,
    depth: np.ndarray | None,
    sm: np.ndarray,
    model: NormalModel,
    contrast: bool,
) -> bool:
    """Steps 3b (with ``spacing_mm``) and 3e (with ``contrast``) on one candidate mask."""
    if spacing_mm is not None:
        one = np.array([1])
        if not _deep_components(comp.astype(np.int64), one, b, spacing_mm, depth).size:
            return False
    return not contrast or _beyond_normal_tail(sm[comp], model)


def _straddles(part: np.ndarray, side: np.ndarray) -> bool:
    """Whether ``part`` has voxels strictly on both sides of the plane.

    ``side`` is the sign (-1, 0, +1) of each voxel's signed distance to the
    plane; a voxel on the plane counts for neither side, so the decision is
    the same for a mirrored image.
    """
    s = side[part]
    return bool((s > 0).any() and (s < 0).any())


def _midline_lesion(
    full_seeds: np.ndarray,
    plane: MirrorPlane,
    voxel_mm: tuple[float, ...],
    min_region_pixels: int,
    min_slices: int,
    b: np.ndarray,
    spacing_mm: tuple[float, ...],
    depth: np.ndarray,
    sm: np.ndarray,
    model: NormalModel,
    contrast: bool = True,
) -> np.ndarray | None:
    """Step 3f: a lesion straddling the mid-sagittal plane, or None.

    The seeds within ``SYMMETRY_TOLERANCE_MM`` of the plane (the band where
    step 3c cannot tell a voxel from its mirror) form components; one that is
    significant (step 3, within the band) and holds seeds on both sides of the
    plane crosses it as one connected structure. Its whole seed component is
    the lesion when it passes step 3b (deep) and, with ``contrast``, step 3e
    (beyond the normal tail): :func:`_passes_evidence`, as the asymmetric
    candidates; the first that passes, the band parts examined largest first.
    """
    d = plane.signed_distance_mm(b.shape[1:], (float(voxel_mm[1]), float(voxel_mm[2])))
    band = np.abs(d) <= SYMMETRY_TOLERANCE_MM
    lab, ids = _significant_components(full_seeds & band[None], min_region_pixels, min_slices)
    side = np.broadcast_to(np.sign(d)[None], lab.shape)
    for i in ids[:MAX_CANDIDATES]:
        part = lab == i
        if not _straddles(part, side):
            continue  # on one side only: a bilateral structure's medial edge
        comp = _touching(full_seeds, part)
        if _passes_evidence(comp, b, spacing_mm, depth, sm, model, contrast):
            return comp
    return None
