"""The learned method: the robust mask refined by the shipped boosted forest."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from tumor3d.errors import InputError
from tumor3d.segmentation.caveats import segmentation_caveats
from tumor3d.segmentation.detect import SliceDetection
from tumor3d.segmentation.methods import register_method
from tumor3d.segmentation.segment import segment_tumor
from tumor3d.segmentation.segment.definition import _WHOLE_TUMOUR
from tumor3d.segmentation.segment.result import SegmentationResult


def learned_prior(
    enhanced: np.ndarray,
    brain_mask: np.ndarray,
    detection: SliceDetection,
    *,
    modality: str,
    min_tumor_pixels: int,
    lesion: Mapping[str, Any] | None,
    spacing_mm: tuple[float, float, float] | None,
    lr_axis: int | None,
    head_exterior: np.ndarray | None,
) -> SegmentationResult:
    """The learned method's prior: the robust method on the same slices.

    One definition for inference (:func:`_segment_learned`) and training
    (``tasks/train.py``), so the model is trained on the prior it is given.
    """
    return segment_tumor(
        enhanced,
        brain_mask,
        detection,
        modality=modality,
        method="robust",
        min_tumor_pixels=min_tumor_pixels,
        lesion=lesion,
        spacing_mm=spacing_mm,
        lr_axis=lr_axis,
        head_exterior=head_exterior,
    )


def learned_caveats(
    tumor: np.ndarray,
    *,
    spacing_mm: tuple[float, float, float] | None,
    head_exterior: np.ndarray | None,
) -> tuple[str, ...]:
    """The caveats of a learned mask: the scan's ends and, on a raw head, the scalp.

    No midline caveat: it speaks of the symmetry rule's blind band, and the
    learned mask is the models' probability cut, not a mask the rule shaped
    (:func:`tumor3d.segmentation.caveats.segmentation_caveats` takes the plane
    only then). Out of fold it did not single out bad volumes either: 8 of the
    27 learned masks it would have named were off by more than 25 % (and 9
    within 10 %), against 28 of all 96 (``reports/learned_cv.md``, "When to
    check").
    """
    return segmentation_caveats(tumor, spacing_mm=spacing_mm, head_exterior=head_exterior)


@register_method(
    "learned",
    description="the robust mask refined by the shipped boosted forest (tumor3d.learned, "
    "reports/model_card.md; on FLAIR its probability averaged with the shipped U-Net's, "
    "segment.learned_cnn), with a probability map and a review",
    measures={
        "flair": _WHOLE_TUMOUR.format(seq="FLAIR"),
        "t2": _WHOLE_TUMOUR.format(seq="T2"),
        "t1c": (
            "tumour core as T1c shows it: the contrast-enhancing lesion with its enclosed "
            "necrotic core, no oedema (BraTS labels 1 + 4, as it was trained); "
            "non-enhancing tumour is mostly missed"
        ),
    },
    uses_lesion=True,
    needs_model=True,
    within_brain_mask=False,  # the forest reads the head's tissue, not the brain mask
    within_detection=False,  # and every slice: its own slices with tumour are its flags
)
def _segment_learned(
    enhanced: np.ndarray,
    brain_mask: np.ndarray,
    detection: SliceDetection,
    *,
    image: np.ndarray | None,
    model: Any,
    learned_cnn: str,
    cnn: Any,
    modality: str,
    min_tumor_pixels: int,
    lesion: Mapping[str, Any] | None,
    spacing_mm: tuple[float, float, float] | None,
    lr_axis: int | None,
    head_exterior: np.ndarray | None,
) -> SegmentationResult:
    """The learned method: the robust mask as a prior, the forest, one 3-D lesion, a review.

    With ``learned_cnn`` auto and a ``cnn``: the mean of the forest's probability and the
    U-Net's, and the review judges the two models' disagreement inside the lesion.
    """
    from tumor3d.learned.forest import ForestModel
    from tumor3d.learned.review import review_features, review_segmentation
    from tumor3d.learned.segment import segment_learned

    if image is None or not isinstance(model, ForestModel):
        raise InputError(
            "the learned method needs the acquired image and a trained model "
            "(image=..., model=tumor3d.learned.shipped.shipped_model(modality))"
        )
    if learned_cnn not in ("auto", "off"):
        raise InputError(f"learned_cnn must be 'auto' or 'off', got {learned_cnn!r}")
    img = np.asarray(image)
    if img.shape != np.shape(enhanced):
        raise InputError(f"image has shape {img.shape} but enhanced has {np.shape(enhanced)}")
    prior = learned_prior(
        enhanced,
        brain_mask,
        detection,
        modality=modality,
        min_tumor_pixels=min_tumor_pixels,
        lesion=lesion,
        spacing_mm=spacing_mm,
        lr_axis=lr_axis,
        head_exterior=head_exterior,
    )
    sp = tuple(float(v) for v in spacing_mm) if spacing_mm is not None else (1.0, 1.0, 1.0)
    seg = segment_learned(
        img, model=model, spacing_mm=sp, modality=modality, lr_axis=lr_axis,
        prior=prior.tumor_mask, cnn=cnn if learned_cnn == "auto" else None,
    )  # fmt: skip
    tumor = seg.mask.copy()
    tumor[tumor.sum(axis=(1, 2)) < int(min_tumor_pixels)] = False
    two = {}  # with the U-Net: the two probabilities averaged, the ensemble's nets (judged)
    if seg.cnn_probability is not None:
        two = {
            "forest_probability": seg.forest_probability,
            "cnn_probability": seg.cnn_probability,
            "cnn_members": seg.cnn_members,
        }
    review = review_segmentation(
        review_features(seg.probability, tumor, sp, prior=prior.tumor_mask, **two)
    )
    has = tumor.any(axis=(1, 2))
    return SegmentationResult(
        tumor_mask=tumor,
        tumor_pixels=tumor.sum(axis=(1, 2)).astype(np.int64),
        reference_centers=np.full(3, np.nan),
        tumor_center_gray=np.full(tumor.shape[0], np.nan),
        selection=np.where(has, "learned", "").astype(str),
        caveats=learned_caveats(tumor, spacing_mm=spacing_mm, head_exterior=head_exterior),
        method="learned",
        probability=seg.probability,
        review=review,
    )
