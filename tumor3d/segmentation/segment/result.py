"""What a segmentation method takes and returns.

The checked inputs every method starts from, the gray levels of ``J`` and the
per-slice :class:`SegmentationResult`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from tumor3d.errors import InputError
from tumor3d.imaging.identity import MODALITIES
from tumor3d.segmentation.caveats import segmentation_caveats
from tumor3d.segmentation.detect import SliceDetection, _check_pair

N_GRAY = 256


@dataclass(frozen=True, eq=False)
class SegmentationResult:
    """Output of :func:`segment_tumor`.

    Attributes
    ----------
    tumor_mask : (z, y, x) ndarray of bool
        Tumour pixels; empty on slices that are not abnormal.
    tumor_pixels : (z,) ndarray of int64
        ``N_i`` of Eq. 8: the number of tumour pixels of each slice.
    reference_centers : (3,) ndarray of float64
        Ascending normal-tissue centres from the patient's normal slices
        (``r_WM < r_GM < r_CSF`` on T2); NaN if there is no normal slice.
    tumor_center_gray : (z,) ndarray of float64
        Gray level of the chosen tumour cluster centre; NaN where the slice
        is not abnormal or no plausible tumour cluster was found.
    selection : (z,) ndarray of str
        How the tumour cluster was chosen: ``""`` (slice not abnormal),
        ``"reference"`` ([A8] assignment), ``"rule"`` (modality rule) or
        ``"none"`` (no plausible cluster, empty mask); ``"lesion"`` (robust
        method, tumour on the slice) and ``"multiotsu"`` (peer).
    fcm_iterations : (z,) ndarray of int64
        Fuzzy c-means iterations of the slice's clustering (paper method);
        -1 where no per-slice FCM ran (not abnormal, robust or peer method).
    fcm_converged : (z,) ndarray of bool
        Whether that FCM reached ``tol`` within ``max_num_iter`` (False where
        none ran).
    caveats : tuple of str
        Where the mask's volume may be wrong, in words
        (:func:`tumor3d.segmentation.caveats.segmentation_caveats`): tumour on the scan's
        first or last slice; a tumour reaching the midline (robust method).
        Empty when there is nothing to say.
    method : str
        The method that ran (``"auto"`` resolved by :func:`resolve_method`):
        ``"robust"``, ``"paper"``, ``"multiotsu"`` or ``"learned"``; what its
        mask holds in words is :func:`lesion_definition`.
    probability : (z, y, x) ndarray of float32, optional
        Learned method: the model's lesion probability per voxel (None for
        the other methods).
    review : tumor3d.learned.review.Review, optional
        Learned method: whether a human should check the mask, its reasons
        and a quality score (None for the other methods).
    """

    tumor_mask: np.ndarray
    tumor_pixels: np.ndarray
    reference_centers: np.ndarray
    tumor_center_gray: np.ndarray
    selection: np.ndarray
    fcm_iterations: np.ndarray | None = None
    fcm_converged: np.ndarray | None = None
    caveats: tuple[str, ...] = ()
    method: str = ""
    probability: np.ndarray | None = None
    review: Any = None

    def __post_init__(self) -> None:
        nz = int(np.asarray(self.tumor_pixels).size)
        if self.fcm_iterations is None:
            object.__setattr__(self, "fcm_iterations", np.full(nz, -1, dtype=np.int64))
        if self.fcm_converged is None:
            object.__setattr__(self, "fcm_converged", np.zeros(nz, dtype=bool))

    def to_records(self) -> list[dict]:
        """One JSON/parquet-friendly row per slice.

        Returns
        -------
        list of dict
            Keys ``slice_index`` (int), ``tumor_pixels`` (int),
            ``tumor_center_gray`` (float, or None where NaN),
            ``selection`` (str), ``fcm_iterations`` (int, -1 where no FCM
            ran) and ``fcm_converged`` (bool).
        """
        return [
            {
                "slice_index": z,
                "tumor_pixels": int(self.tumor_pixels[z]),
                "tumor_center_gray": (
                    None
                    if not np.isfinite(self.tumor_center_gray[z])
                    else float(self.tumor_center_gray[z])
                ),
                "selection": str(self.selection[z]),
                "fcm_iterations": int(self.fcm_iterations[z]),
                "fcm_converged": bool(self.fcm_converged[z]),
            }
            for z in range(self.tumor_pixels.size)
        ]


def _checked_inputs(
    enhanced: np.ndarray,
    brain_mask: np.ndarray,
    detection: SliceDetection,
    modality: str,
    min_tumor_pixels: int,
) -> tuple[np.ndarray, np.ndarray, str]:
    """The robust and peer methods' checks: ``(img, brain, modality)`` or an InputError."""
    img, brain = _check_pair(enhanced, brain_mask)
    if not isinstance(detection, SliceDetection):
        raise InputError("detection must be a SliceDetection")
    if len(detection) != img.shape[0]:
        raise InputError(f"detection has {len(detection)} slices but enhanced has {img.shape[0]}")
    mod = modality.strip().lower() if isinstance(modality, str) else modality
    if mod not in MODALITIES:
        raise InputError(f"unknown modality {modality!r}: expected one of {MODALITIES}")
    if int(min_tumor_pixels) < 1:
        raise InputError(f"min_tumor_pixels must be >= 1, got {min_tumor_pixels}")
    return img, brain, mod


def _slice_result(
    tumor: np.ndarray,
    detection: SliceDetection,
    *,
    how: str,
    center: np.ndarray,
    ref: np.ndarray,
    min_tumor_pixels: int,
    method: str,
    caveat_keywords: dict[str, Any],
) -> SegmentationResult:
    """Slices under ``min_tumor_pixels`` cleared; the per-slice records and the caveats."""
    small = tumor.sum(axis=(1, 2)) < int(min_tumor_pixels)
    tumor[small] = False
    has = tumor.any(axis=(1, 2))
    selection = np.where(has, how, np.where(detection.abnormal, "none", ""))
    center = np.where(has, center, np.nan)
    return SegmentationResult(
        tumor_mask=tumor,
        tumor_pixels=tumor.sum(axis=(1, 2)).astype(np.int64),
        reference_centers=ref,
        tumor_center_gray=center,
        selection=selection.astype(str),
        caveats=segmentation_caveats(tumor, **caveat_keywords),
        method=method,
    )
