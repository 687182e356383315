"""The multi-Otsu peer (``segment.method: multiotsu``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from scipy import ndimage as ndi
from skimage.filters import threshold_multiotsu

from tumor3d.errors import InputError
from tumor3d.segmentation.detect import SliceDetection
from tumor3d.segmentation.lesion import lesion_params
from tumor3d.segmentation.methods import register_method
from tumor3d.segmentation.segment.result import (
    N_GRAY,
    SegmentationResult,
    _checked_inputs,
    _slice_result,
)


@register_method(
    "multiotsu",
    description="the peer: the brightest multi-Otsu class of the brain, its largest 3-D component",
    measures=(
        "the peer: the brightest of the multi-Otsu classes of the brain on {seq}, its "
        "largest 3-D component"
    ),
    within_detection=False,  # the whole brain at once: the detection is ignored
)
def segment_multiotsu(
    enhanced: np.ndarray,
    brain_mask: np.ndarray,
    detection: SliceDetection,
    *,
    modality: str,
    min_tumor_pixels: int,
    multiotsu_classes: int,
    lesion: Mapping[str, Any] | None,
    spacing_mm: tuple[float, float, float] | None,
    head_exterior: np.ndarray | None,
) -> SegmentationResult:
    """The peer (:func:`multiotsu_peer`); ``detection`` only names the abnormal slices."""
    img, brain, _ = _checked_inputs(enhanced, brain_mask, detection, modality, min_tumor_pixels)
    nz = img.shape[0]
    params = lesion_params(lesion)
    if not 2 <= int(multiotsu_classes) <= 6:
        raise InputError(f"multiotsu_classes must lie in [2, 6], got {multiotsu_classes}")
    tumor = multiotsu_peer(img, brain, classes=int(multiotsu_classes))
    return _slice_result(
        tumor,
        detection,
        how="multiotsu",
        center=np.full(nz, np.nan),
        ref=np.full(3, np.nan),
        min_tumor_pixels=min_tumor_pixels,
        method="multiotsu",
        caveat_keywords={
            "plane": None,  # the peer has no symmetry rule
            "spacing_mm": spacing_mm,
            "min_region_mm2": params["min_region_mm2"],
            "min_slices": params["min_slices"],
            "midline_lesion": False,
            "head_exterior": head_exterior,
        },
    )


def multiotsu_peer(img: np.ndarray, brain: np.ndarray, *, classes: int = 4) -> np.ndarray:
    """The simple peer: brightest multi-Otsu class of the brain, largest 3-D component.

    Thresholds from :func:`skimage.filters.threshold_multiotsu` on the
    brain gray levels pooled over all slices; the class above the highest
    threshold; its largest 26-connected component. Empty if the brain has
    fewer than ``classes`` distinct gray levels.
    """
    vals = img[brain]
    if vals.size == 0 or np.unique(vals).size < classes:
        return np.zeros(img.shape, dtype=bool)
    hist = np.bincount(vals, minlength=N_GRAY)
    t = threshold_multiotsu(hist=hist, classes=classes)[-1]
    bright = brain & (img > t)
    labels, n = ndi.label(bright, structure=np.ones((3, 3, 3), dtype=bool))
    if n == 0:
        return bright
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return labels == int(np.argmax(sizes))
