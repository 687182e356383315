"""Abnormal-slice detection by counting histogram modes (specification section 2).

A normal slice holds three tissues (white matter, gray matter, CSF), so the
gray-level histogram of its brain region has three modes; a tumour adds a
fourth (Arakeri & Reddy 2013, Eq. 1, after Castro et al. 2007). The mode
count ``k`` and the peak gray levels also seed the fuzzy c-means of
section 3.

The package: the per-slice detection here (:func:`detect_abnormal_slices`, which looks
``patient_lesion`` up in this namespace), :mod:`~tumor3d.segmentation.detect.result` (what it
returns), :mod:`~tumor3d.segmentation.detect.methods` (the methods and the paper's premise)
and :mod:`~tumor3d.segmentation.detect.modes` (mode counting). The public names are
importable from here.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from tumor3d.errors import InputError
from tumor3d.imaging.identity import MODALITIES
from tumor3d.segmentation.detect.methods import DETECT_METHODS, paper_premise_holds
from tumor3d.segmentation.detect.modes import (
    _check_mode_params,
    _modes_from_counts,
    count_histogram_modes,
)
from tumor3d.segmentation.detect.result import HistogramModes, SliceDetection
from tumor3d.segmentation.lesion import area_in_pixels, patient_lesion

__all__ = [
    "HistogramModes",
    "SliceDetection",
    "count_histogram_modes",
    "detect_abnormal_slices",
    "paper_premise_holds",
]


def _check_pair(enhanced: object, brain_mask: object) -> tuple[np.ndarray, np.ndarray]:
    """Validate ``J`` and ``M_brain``; return them as uint8 and bool (copies only if needed).

    Accepts any integer or float ``enhanced`` whose values are whole gray
    levels 0-255, and any ``brain_mask`` of 0/1 values, since both may come
    back from storage as another dtype.
    """
    img = np.asarray(enhanced)
    mask = np.asarray(brain_mask)
    if img.ndim != 3:
        raise InputError(f"enhanced must be a 3-D (z, y, x) array, got {img.ndim} dimension(s)")
    if mask.shape != img.shape:
        raise InputError(f"brain_mask shape {mask.shape} does not match enhanced shape {img.shape}")
    if img.dtype != np.uint8:
        if not (np.issubdtype(img.dtype, np.integer) or np.issubdtype(img.dtype, np.floating)):
            raise InputError(f"enhanced must hold gray levels 0-255, got dtype {img.dtype}")
        if img.size and (
            not np.all(np.isfinite(img))
            or img.min() < 0
            or img.max() > 255
            or np.any(img != np.round(img))
        ):
            raise InputError("enhanced must hold whole gray levels 0-255 (the J of section 1)")
        img = img.astype(np.uint8)
    if mask.dtype != bool:
        if not (np.issubdtype(mask.dtype, np.integer) or np.issubdtype(mask.dtype, np.floating)):
            raise InputError(f"brain_mask must be boolean, got dtype {mask.dtype}")
        if mask.size and not np.all((mask == 0) | (mask == 1)):
            raise InputError("brain_mask must be boolean (only 0 and 1 values)")
        mask = mask.astype(bool)
    return img, mask


def _brain_histograms(img: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """(z, 256) histogram of the brain pixels of every slice, in one bincount."""
    nz = img.shape[0]
    zz = np.broadcast_to(np.arange(nz, dtype=np.intp)[:, None, None], img.shape)
    keys = zz[mask] * 256 + img[mask].astype(np.intp)
    return np.bincount(keys, minlength=nz * 256).reshape(nz, 256)


def detect_abnormal_slices(
    enhanced: np.ndarray,
    brain_mask: np.ndarray,
    *,
    n_bins: int = 64,
    smoothing_sigma_bins: float = 1.0,
    min_mode_area: float = 0.005,
    min_peak_distance_bins: float = 3,
    min_valley_significance: float = 3.0,
    abnormal_min_modes: int = 4,
    min_brain_pixels: int = 500,
    method: str = "auto",
    modality: str | None = None,
    lesion: Mapping[str, Any] | None = None,
    lesion_min_slice_mm2: float = 20.0,
    spacing_mm: tuple[float, float, float] | None = None,
    lr_axis: int | None = None,
) -> SliceDetection:
    """Flag the abnormal slices of a patient (specification section 2).

    Two methods (``DetectConfig.method``; ``"auto"``, the default, is
    ``"robust"`` on FLAIR and T1c, on T2 ``"histogram"`` where the paper's
    premise holds (:func:`paper_premise_holds`: three tissue modes on
    nearly every slice) and ``"robust"`` otherwise, and ``"histogram"`` when
    ``modality`` is None, for the reason given in
    :func:`tumor3d.segmentation.segment.resolve_method`); both record the histogram modes
    of every slice (``n_modes``, ``peaks_gray``: the seeds of the paper's
    segmentation).

    ``method="robust"``: a slice is abnormal when it holds at least
    ``lesion_min_slice_mm2`` of a lesion found by
    :func:`tumor3d.segmentation.lesion.segment_hyperintense_lesion` over the whole
    patient: the normal-tissue intensity model is learned across all
    slices (median / MAD of the smoothed brain), a region is abnormal when
    it falls above it over a significant cross-section on at least
    ``lesion["min_slices"]`` consecutive slices (consistency between
    neighbours). The lesion is returned in ``SliceDetection.lesion``.
    Measured on BraTS FLAIR at 2 mm / 5 mm: recall and specificity in
    ``reports/segmentation.md``; the histogram method flags 7-27 % of the
    tumour slices there.

    ``method="histogram"``: the paper's mode count. For every slice ``z``
    the histogram of ``enhanced[z]`` over
    ``brain_mask[z]`` only [A4] goes through :func:`count_histogram_modes`;
    the slice is abnormal iff ``k >= abnormal_min_modes`` [A6] and it has at
    least ``min_brain_pixels`` brain pixels (end slices with a sliver of
    brain have unreliable histograms and are never abnormal).

    Parameters
    ----------
    enhanced : (z, y, x) ndarray of uint8
        ``J`` of section 1 (another dtype is accepted if it holds whole gray
        levels 0-255).
    brain_mask : (z, y, x) ndarray of bool
        ``M_brain`` of section 1 (0/1 values of another dtype are accepted).
    n_bins, smoothing_sigma_bins, min_mode_area, min_peak_distance_bins, min_valley_significance
        See :func:`count_histogram_modes`.
    abnormal_min_modes : int
        ``k`` from which a slice is abnormal (4: three tissues plus tumour).
    min_brain_pixels : int
        Slices with fewer brain pixels are never abnormal.
    method : {"auto", "robust", "histogram"}
        See above.
    modality : {"t2", "flair", "t1c"} or None
        Sequence (robust method only): on T2 the CSF-bright voxels are
        excluded from the lesion. None = no CSF rule (FLAIR, T1c). The
        adapter passes the scan's modality.
    lesion : mapping, optional
        Robust method: keywords of
        :func:`tumor3d.segmentation.lesion.segment_hyperintense_lesion` (the fields of
        ``tumor3d.config.LesionConfig``, ``detect.lesion`` of the pipeline);
        None or missing keys = :data:`tumor3d.segmentation.lesion.LESION_DEFAULTS`.
    lesion_min_slice_mm2 : float
        Robust method: a slice is abnormal when it holds at least this much
        lesion (mm2 through the pixel spacing, as pixels of 1 mm on coarser
        pixels: :func:`tumor3d.segmentation.lesion.area_in_pixels`; the lesion itself must
        be significant elsewhere).
    spacing_mm : (3,) tuple of float, optional
        Voxel spacing ``(slice step, row, column)`` in mm (robust method: the
        in-plane lengths and areas and the depth rule of
        :mod:`tumor3d.segmentation.lesion`, ``lesion_min_slice_mm2``); None = 1 mm voxels.
        The adapter passes the scan's.
    lr_axis : {1, 2} or None
        Robust method: the left-right array axis (symmetry rule of
        :mod:`tumor3d.segmentation.lesion`, :func:`~tumor3d.segmentation.lesion.left_right_axis`
        of the
        scan's affine); None skips the rule. The adapter passes it.

    Returns
    -------
    SliceDetection

    Raises
    ------
    InputError
        On wrong dimensions, dtypes, mismatched shapes or parameters.
    """
    img, mask = _check_pair(enhanced, brain_mask)
    _check_mode_params(
        n_bins, smoothing_sigma_bins, min_mode_area, min_peak_distance_bins, min_valley_significance
    )
    if int(abnormal_min_modes) < 1:
        raise InputError(f"abnormal_min_modes must be >= 1, got {abnormal_min_modes}")
    if int(min_brain_pixels) < 0:
        raise InputError(f"min_brain_pixels must be >= 0, got {min_brain_pixels}")
    hists = _brain_histograms(img, mask)
    modes = [
        _modes_from_counts(
            hist,
            n_bins=int(n_bins),
            sigma=float(smoothing_sigma_bins),
            min_area=float(min_mode_area),
            min_distance=float(min_peak_distance_bins),
            min_significance=float(min_valley_significance),
        )
        for hist in hists
    ]
    n_modes = np.array([m.n_modes for m in modes], dtype=np.int64)
    brain_pixels = hists.sum(axis=1).astype(np.int64)
    if method not in DETECT_METHODS:
        raise InputError(f"unknown detect method {method!r}: expected one of {DETECT_METHODS}")
    if method == "auto":
        mod = modality.strip().lower() if isinstance(modality, str) else None
        if mod in ("flair", "t1c"):
            method = "robust"
        elif mod == "t2" and not paper_premise_holds(n_modes, brain_pixels):
            method = "robust"
        else:
            method = "histogram"
    model = None
    if method == "histogram":
        flagged = n_modes >= int(abnormal_min_modes)
    else:
        mod = modality.strip().lower() if isinstance(modality, str) else "flair"
        if mod not in MODALITIES:
            raise InputError(f"unknown modality {modality!r}: expected one of {MODALITIES}")
        model = patient_lesion(
            img, mask, modality=mod, lesion=lesion, spacing_mm=spacing_mm, lr_axis=lr_axis
        )
        pixel_mm2 = 1.0 if spacing_mm is None else float(spacing_mm[1]) * float(spacing_mm[2])
        flagged = model.mask.sum(axis=(1, 2)) >= area_in_pixels(lesion_min_slice_mm2, pixel_mm2)
    abnormal = flagged & (brain_pixels >= int(min_brain_pixels))
    return SliceDetection(
        n_modes=n_modes,
        abnormal=abnormal,
        peaks_gray=tuple(m.peaks_gray for m in modes),
        brain_pixels=brain_pixels,
        lesion=model,
    )
