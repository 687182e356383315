"""The patient lesion model: steps 1 to 6 of :mod:`tumor3d.segmentation.lesion` in order.

:func:`segment_hyperintense_lesion` validates, converts the lengths to
pixels and works inside the brain's bounding box (:func:`_segment_box`);
:func:`patient_lesion` is the call of the detector and the segmenter, with
the configuration checked over :data:`LESION_DEFAULTS`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from tumor3d.errors import InputError
from tumor3d.segmentation.lesion.candidates import MAX_CANDIDATES, _candidates
from tumor3d.segmentation.lesion.cavity import _asymmetric_cavity, _cavity_wall, _fill_enclosed
from tumor3d.segmentation.lesion.growth import SATELLITE_MM, _reached, _refine
from tumor3d.segmentation.lesion.normal import (
    NormalModel,
    _csf_threshold,
    _passing_components,
    _smooth_in_brain,
    normal_model,
)
from tumor3d.segmentation.lesion.pixels import _blur_reach, _pixel_lengths
from tumor3d.segmentation.lesion.regions import _bounding_box
from tumor3d.segmentation.lesion.symmetry import MirrorPlane, _shifted_plane, symmetry_plane

#: A lesion covering more than this share of the brain violates the premise of the
#: median / MAD model (breakdown point 50 %): no lesion is reported.
MAX_BRAIN_FRACTION = 0.5


@dataclass(frozen=True, eq=False)
class LesionResult:
    """Output of :func:`segment_hyperintense_lesion`.

    Attributes
    ----------
    mask : (z, y, x) ndarray of bool
        The lesion (whole tumour).
    model : NormalModel
        The normal-tissue model used.
    lesion_gray : float
        Median gray level of the seed component (NaN without lesion).
    grow_threshold : float
        Partial-volume midpoint used at the border (NaN without lesion).
    n_components : int
        Significant seed components found (before keeping the largest).
    plane : MirrorPlane or None
        The mid-sagittal plane of step 3c, in the whole volume's pixel frame;
        None when the symmetry rule did not run (no left-right axis, or no
        brain).
    midline : bool
        The lesion was found by step 3f (it straddles the plane and no
        asymmetric seed confirmed it: its brightness and depth alone).
    """

    mask: np.ndarray
    model: NormalModel
    lesion_gray: float
    grow_threshold: float
    n_components: int
    plane: MirrorPlane | None = None
    midline: bool = False


#: The configurable keywords of :func:`segment_hyperintense_lesion` and their defaults
#: (``tumor3d.config.LesionConfig`` holds the same, the pipeline's ``detect.lesion``).
LESION_DEFAULTS: dict[str, float | int | bool] = {
    "smoothing_mm": 2.0,
    "seed_sigmas": 2.0,
    "min_region_mm2": 50.0,
    "min_slices": 2,
    "keep_largest": True,
    "refine_boundary": True,
    "fill_core": True,
    "boundary_mm": 3.0,
    "floor_sigmas": 1.0,
}


def lesion_params(lesion: Mapping[str, Any] | None) -> dict[str, Any]:
    """Checked keywords of the lesion model: ``lesion`` over :data:`LESION_DEFAULTS`.

    Raises
    ------
    InputError
        On an unknown key or an out-of-range value (naming it).
    """
    given = dict(lesion or {})
    unknown = sorted(set(given) - set(LESION_DEFAULTS))
    if unknown:
        raise InputError(
            f"unknown lesion parameter(s) {unknown}: expected {sorted(LESION_DEFAULTS)}"
        )
    p = {**LESION_DEFAULTS, **given}
    if not 0.0 <= float(p["smoothing_mm"]) <= 20.0:
        raise InputError(f"lesion smoothing_mm must lie in [0, 20], got {p['smoothing_mm']}")
    if not float(p["seed_sigmas"]) > 0.0:
        raise InputError(f"lesion seed_sigmas must be > 0, got {p['seed_sigmas']}")
    if not float(p["min_region_mm2"]) > 0.0:
        raise InputError(f"lesion min_region_mm2 must be > 0, got {p['min_region_mm2']}")
    if int(p["min_slices"]) < 1:
        raise InputError(f"lesion min_slices must be >= 1, got {p['min_slices']}")
    if not 0.0 <= float(p["boundary_mm"]) <= 20.0:
        raise InputError(f"lesion boundary_mm must lie in [0, 20], got {p['boundary_mm']}")
    if not float(p["floor_sigmas"]) >= 0.0:
        raise InputError(f"lesion floor_sigmas must be >= 0, got {p['floor_sigmas']}")
    return {
        "smoothing_mm": float(p["smoothing_mm"]),
        "seed_sigmas": float(p["seed_sigmas"]),
        "min_region_mm2": float(p["min_region_mm2"]),
        "min_slices": int(p["min_slices"]),
        "keep_largest": bool(p["keep_largest"]),
        "refine_boundary": bool(p["refine_boundary"]),
        "fill_core": bool(p["fill_core"]),
        "boundary_mm": float(p["boundary_mm"]),
        "floor_sigmas": float(p["floor_sigmas"]),
    }


def patient_lesion(
    enhanced: np.ndarray,
    brain: np.ndarray,
    *,
    modality: str,
    lesion: Mapping[str, Any] | None = None,
    spacing_mm: tuple[float, float, float] | None = None,
    lr_axis: int | None = None,
) -> LesionResult:
    """The lesion model as the detector and the segmenter call it.

    :func:`segment_hyperintense_lesion` with ``lesion`` checked over
    :data:`LESION_DEFAULTS` (the pipeline's ``detect.lesion`` section) and
    ``spacing_mm`` None read as isotropic.
    """
    return segment_hyperintense_lesion(
        enhanced,
        brain,
        modality=modality,
        spacing_mm=(1.0, 1.0, 1.0) if spacing_mm is None else tuple(spacing_mm),
        lr_axis=lr_axis,
        **lesion_params(lesion),
    )


def segment_hyperintense_lesion(
    enhanced: np.ndarray,
    brain: np.ndarray,
    *,
    modality: str,
    smoothing_mm: float = 2.0,
    seed_sigmas: float = 2.0,
    min_region_mm2: float = 50.0,
    min_slices: int = 2,
    keep_largest: bool = True,
    refine_boundary: bool = True,
    fill_core: bool = True,
    tips: bool = True,
    boundary_mm: float = 3.0,
    floor_sigmas: float = 1.0,
    allowed_slices: np.ndarray | None = None,
    spacing_mm: tuple[float, float, float] = (1.0, 1.0, 1.0),
    reject_superficial: bool = True,
    lr_axis: int | None = None,
) -> LesionResult:
    """Segment the hyperintense whole tumour of a patient (package docstring steps 1-6).

    Parameters
    ----------
    enhanced : (z, y, x) ndarray of uint8
        ``J`` of section 1 (0 outside the brain).
    brain : (z, y, x) ndarray of bool
        ``M_brain``.
    modality : {"t2", "flair", "t1c"}
        Sequence; T2 excludes CSF-bright voxels (step 6).
    smoothing_mm : float
        In-plane Gaussian sigma of step 1, mm. Every in-plane length and area
        of the model is given in mm and mm2 and converted to pixels
        through ``spacing_mm`` (:func:`_pixel_lengths`), so that a scan with
        0.5 mm or 2 mm pixels is regularised like one with 1 mm pixels (the
        values were chosen on 1 mm BraTS pixels, where they are the pixel
        counts they replaced).
    seed_sigmas : float
        Seed threshold in robust standard deviations above the median.
    min_region_mm2 : float
        Smallest cross-section (mm2) of a significant component on a
        slice.
    min_slices : int
        Consecutive slices on which a significant component must reach that
        cross-section.
    keep_largest : bool
        Keep only the largest significant component.
    refine_boundary : bool
        Step 4 (partial-volume growth at the border) and step 5c (the same
        around a joined cavity).
    fill_core : bool
        Step 5 (enclosed necrotic core / cavities).
    tips : bool
        Let the step-4 growth reach one slice beyond the seed component
        (the lesion's tip on the next thick slice).
    boundary_mm : float
        Width (mm) of the local partial-volume growth after step 4
        (:func:`_grow_local`), grown one pixel ring at a time; 0 disables it.
        3 mm = the extent (1.5 sigma) of the default 2 mm blur.
    floor_sigmas : float
        The growth's floor, robust SDs above the median (chosen by
        leave-one-case-out, see ``reports/segmentation.md``).
    allowed_slices : (z,) array_like of bool, optional
        Slices where the lesion may lie (e.g. a detection); others are cleared
        at the end.
    spacing_mm : (3,) tuple of float
        Voxel spacing ``(slice step, row, column)`` in mm: the in-plane
        lengths and areas above (through a square pixel of the same area:
        rows and columns of different spacing get the same pixel lengths),
        the depth of step 3b (only its ratios matter there), the mirror
        tolerance and the mid-sagittal plane of step 3c (in mm).
    reject_superficial : bool
        Step 3b: keep only candidates at least as deep as the brain's median
        depth. False turns step 3d off too (it needs that depth).
    lr_axis : {1, 2} or None
        Array axis running left-right (:func:`left_right_axis` of the scan's
        affine), for step 3c; None skips it (e.g. sagittal slices). The
        mirror is about the mid-sagittal plane estimated from the image
        (:func:`symmetry_plane`), which may be yawed against this axis.

    Returns
    -------
    LesionResult
    """
    img = np.asarray(enhanced)
    b = np.asarray(brain, dtype=bool)
    if img.shape != b.shape or img.ndim != 3:
        raise InputError(f"enhanced {img.shape} and brain {b.shape} must be equal 3-D shapes")
    sp = np.asarray(spacing_mm, dtype=np.float64).ravel()
    if sp.size != 3 or not (np.all(np.isfinite(sp)) and np.all(sp > 0)):
        raise InputError(f"spacing_mm must be three positive numbers (mm), got {spacing_mm}")
    voxel_mm = tuple(float(v) for v in sp)
    px = _pixel_lengths(voxel_mm, smoothing_mm, min_region_mm2, boundary_mm)
    smoothing_px = px.smoothing
    empty_model = NormalModel(float("nan"), float("nan"), float("nan"), float("inf"))
    if not b.any():
        return LesionResult(np.zeros(b.shape, bool), empty_model, float("nan"), float("nan"), 0)
    # work inside the brain's bounding box (plus the smoothing support): outside it
    # there is no brain, so nothing changes, and the filters cost less
    pad = int(np.ceil(4 * float(smoothing_px))) + 1
    box = _bounding_box(b, pad)
    res = _segment_box(
        img[box],
        b[box],
        modality,
        smoothing_px,
        seed_sigmas,
        px.min_region,
        min_slices,
        keep_largest,
        refine_boundary,
        fill_core,
        tips,
        px.rings,
        floor_sigmas,
        voxel_mm if reject_superficial else None,
        lr_axis,
        voxel_mm,
        local_px=px.local_sigma,
    )
    mask = np.zeros(b.shape, dtype=bool)
    mask[box] = res.mask
    if allowed_slices is not None:
        mask[~np.asarray(allowed_slices, dtype=bool)] = False
    plane = res.plane
    if plane is not None:  # from the box's pixel frame to the volume's
        plane = _shifted_plane(plane, box[1].start * voxel_mm[1], box[2].start * voxel_mm[2])
    return LesionResult(
        mask, res.model, res.lesion_gray, res.grow_threshold, res.n_components, plane, res.midline
    )


def _segment_box(
    img,
    b,
    modality,
    smoothing_px,
    seed_sigmas,
    min_region_pixels,
    min_slices,
    keep_largest,
    refine_boundary,
    fill_core,
    tips,
    boundary_rings,
    floor_sigmas,
    spacing_mm=None,
    lr_axis=None,
    voxel_mm=(1.0, 1.0, 1.0),
    *,
    local_px,
) -> LesionResult:
    """:func:`segment_hyperintense_lesion` on the brain's bounding box.

    Its in-plane lengths and areas are pixels (``smoothing_px``, ``min_region_pixels``,
    ``boundary_rings``, ``local_px``: see :func:`_pixel_lengths`).
    """
    sm = _smooth_in_brain(img, b, float(smoothing_px))
    model = normal_model(sm, img, b, seed_sigmas, modality)
    plane = None if lr_axis is None else symmetry_plane(sm, b, model, int(lr_axis), voxel_mm)
    # step 3d on FLAIR only: there the CSF is dark, so the deep bilateral bright structures
    # of T2 (ventricles) and T1c (choroid plexus, deep veins) are no seeds
    args = (sm, img, b, smoothing_px, min_region_pixels, min_slices, keep_largest)
    crossing = modality == "flair"
    # step 3e on FLAIR only: T2's and T1c's lesions are less conspicuous (package docstring)
    contrast = modality == "flair"
    not_csf, labels, ids, satellites, across, midline = _candidates(
        model, *args, spacing_mm, plane, voxel_mm, crossing, contrast
    )
    if ids.size and np.isfinite(model.csf_threshold):
        # step 6, second pass: a voxel is CSF when it is nearer the CSF level than the
        # lesion's own gray (partial-volume midpoint), now that the lesion gray is known;
        # a lesion brighter than the seed level moves the threshold up
        lesion_gray0 = float(np.median(img[np.isin(labels, ids[:1])]))
        csf_t = max(model.csf_threshold, _csf_threshold(img, b, lesion_gray0))
        if csf_t > model.csf_threshold:
            model = NormalModel(model.median, model.sigma, model.seed_threshold, csf_t)
            not_csf, labels, ids, satellites, across, midline = _candidates(
                model, *args, spacing_mm, plane, voxel_mm, crossing, contrast
            )
    if ids.size == 0:
        return LesionResult(np.zeros(b.shape, bool), model, float("nan"), float("nan"), 0, plane)
    core = np.isin(labels, ids[:1] if keep_largest else ids)
    lesion_gray = float(np.median(img[core]))
    grow_t = 0.5 * (lesion_gray + model.median)
    mask = core
    crossed = None  # what step 3d added beyond the lesion
    if refine_boundary:
        refine = (img, b & not_csf, grow_t, _blur_reach(smoothing_px), tips, model)
        mask = _refine(core, *refine, floor_sigmas, boundary_rings, local_px=local_px)
        if across is not None and across.any():
            # step 3d: the part across the midline is decided by the partial-volume rule
            # alone, without the boundary rings' weaker evidence
            crossed = _refine(across, *refine, floor_sigmas, 0, local_px=local_px) & ~mask
            mask = mask | crossed
        if satellites is not None and satellites.any():
            # step 4b: a satellite the refined lesion reaches (on FLAIR / T2: comes within
            # SATELLITE_MM of) is the same lesion
            reach_mm = SATELLITE_MM if modality in ("flair", "t2") else 0.0
            # joining by proximity alone (within SATELLITE_MM, not touching) is weaker
            # evidence than touching: on FLAIR the satellite must then pass step 3e
            near_ok = None
            if contrast and reach_mm > 0.0:
                near_ok = _passing_components(satellites, sm, model)
            for _ in range(MAX_CANDIDATES):
                if near_ok is None:
                    reached = _reached(satellites & ~core, mask, reach_mm, voxel_mm)
                else:
                    reached = _reached(satellites & ~core, mask, 0.0, voxel_mm)
                    reached |= _reached(near_ok & ~core, mask, reach_mm, voxel_mm)
                if not reached.any():
                    break
                core = core | reached
                # refined around what joined (the rest of the lesion keeps its border)
                mask = mask | _refine(
                    reached, *refine, floor_sigmas, boundary_rings, local_px=local_px
                )
    elif across is not None and across.any():
        crossed = across & ~core
        mask = core | across
    # the lesion without what step 3d added across the midline: step 5b's extent
    own = None if crossed is None else mask & ~crossed
    if fill_core:
        mask = _fill_enclosed(mask, b, img, model.median)
        if plane is not None and modality != "t2" and mask.any():
            # on T2 the fluid is bright (step 6); on FLAIR / T1c it is dark
            reach = _blur_reach(smoothing_px)
            mask, cavity = _asymmetric_cavity(
                mask,
                sm,
                b,
                model,
                seed_sigmas,
                reach,
                plane,
                voxel_mm,
                min_region_pixels,
                min_slices,
                extent_of=own,
            )
            if refine_boundary and cavity.any():
                mask = _cavity_wall(
                    mask, cavity, img, b & not_csf, grow_t, reach, model, floor_sigmas,
                    boundary_rings, local_px,
                )  # fmt: skip
    mask &= b
    if np.count_nonzero(mask) > MAX_BRAIN_FRACTION * np.count_nonzero(b):
        # the model's premise (the lesion is a minority of the brain, so the median and
        # the MAD describe normal tissue) is violated: what lies "outside" it is a
        # normal tissue class (e.g. grey matter of a strongly bimodal parenchyma)
        return LesionResult(np.zeros(b.shape, bool), model, float("nan"), float("nan"), 0, plane)
    return LesionResult(mask, model, lesion_gray, grow_t, int(ids.size), plane, midline)
