"""Adapter of the segment-tumor stage (spec section 3).

The stage is the call of :func:`tumor3d.segmentation.patient.segment_patient`
with its declared inputs: the robust method reuses the lesion model of the
detect stage (its ``lesion`` artifact: mask and scalars, the mask read only
then); when the detection did not compute it (histogram detection), the
method computes it with the parameters that artifact records
(``detect.lesion``). The acquired scan is read for the learned method only.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pandas as pd

from tumor3d.config import SegmentConfig
from tumor3d.learned.bundle import ModelSet, model_set, unpack_models
from tumor3d.segmentation.detect import SliceDetection
from tumor3d.segmentation.patient import segment_patient, stored_detection
from tumor3d.storage.nifti import probability_for_storage
from tumor3d.tasks.kinds import Artifact, Volume
from tumor3d.tasks.spec import Input, Metric, StageResult, scan_spacing_mm, stage

__all__ = ["SPEC", "load_detection"]


def load_detection(
    detection: pd.DataFrame, lesion: Artifact, *, with_lesion: bool = True
) -> tuple[SliceDetection, dict[str, Any]]:
    """The detect stage's :class:`SliceDetection` and its lesion artifact's metadata.

    With ``with_lesion``, the lesion model it computed (if it did) is put back
    on the detection (:func:`tumor3d.segmentation.patient.stored_detection`), so
    the robust method does not compute it again.
    """
    meta = lesion.metadata["lesion"]
    records = detection.to_dict("records")
    det = stored_detection(records, meta, lambda: lesion.load().array, with_lesion=with_lesion)
    return det, meta


@stage(
    "segment-tumor",
    entry=segment_patient,
    config=SegmentConfig,
    inputs={
        "scan": Input("scan", "ingest-scan.scan", load=False),  # the image for `learned` only
        "enhanced": Input("image", "preprocess.enhanced"),
        "brain_mask": Input("mask", "preprocess.brain_mask"),
        "detection": Input("table", "detect-abnormal.detection"),
        "lesion": Input("mask", "detect-abnormal.lesion", load=False),  # the model, if computed
        "head_exterior": Input("mask", "preprocess.head_exterior"),
        # the user's segmentation on the scan's grid (--segmentation)
        "given_mask": Input("mask", "given:segmentation", load=False, optional=True),
        # a user's trained models (segment.learned_models): their content is in the key
        "given_models": Input("models", "given:models", load=False, optional=True),
    },
    # tumor_probability: the learned method only
    outputs={"tumor_mask_slices": "mask", "segmentation": "table", "tumor_probability": "image"},
    metrics={
        "modality": Metric("modality", "the input's modality (t2, flair, t1c)"),
        "segment_method": Metric("segment_method", "the segmentation method that ran"),
        "measured": Metric("measured", "what the mask, and so every volume, holds, in words"),
        "segment_model": Metric(
            "segment_model", "learned method: forest, or forest + U-Net mean (else empty)"
        ),
    },
)
def segment(
    scan: Artifact,
    enhanced: Volume,
    brain_mask: Volume,
    detection: pd.DataFrame,
    lesion: Artifact,
    head_exterior: Volume,
    config: SegmentConfig,
    given_mask: Artifact | None = None,
    given_models: Artifact | None = None,
) -> StageResult:
    """Tumour segmentation: the lesion model (robust), wavelet + histogram FCM, or the peer.

    ``given_mask``, the user's segmentation on the scan's grid (``--segmentation``,
    its file name in the artifact's ``given_file``), replaces the method: stored as
    is, method ``"given"``; as an input artifact its content enters the cache key.
    ``given_models``, a user's trained models (``segment.learned_models``, packed:
    :func:`tumor3d.learned.bundle.pack_models`), replace the shipped ones; read only
    for the learned method.
    """
    modality = scan.metadata["modality"]
    seg = segment_patient(
        enhanced.array,
        brain_mask.array,
        detection.to_dict("records"),
        affine=enhanced.affine,
        modality=modality,
        spacing_mm=scan_spacing_mm(scan),
        lesion=lesion.metadata["lesion"],
        lesion_mask=lambda: lesion.load().array,  # read only if the method reuses the model
        head_exterior=head_exterior.array,
        image=lambda: scan.load().array,  # read only for the learned method
        given=None if given_mask is None else given_mask.load(),
        given_name=None if given_mask is None else given_mask.metadata.get("given_file"),
        models=None if given_models is None else _own_models(given_models, modality, config),
        **config.model_dump(),
    )
    artifacts = {
        "tumor_mask_slices": Volume(seg.result.tumor_mask, seg.affine),
        "segmentation": seg.records,
    }
    if seg.result.probability is not None:  # the learned method's, stored to 1/255
        probability = probability_for_storage(seg.result.probability)
        artifacts["tumor_probability"] = Volume(probability, seg.affine)
    return StageResult(artifacts=artifacts, values=seg.values)


SPEC = segment


def _own_models(given: Artifact, modality: str, config: SegmentConfig) -> Callable[[], ModelSet]:
    """A user's models for ``modality`` (``segment.learned_models``), read when called."""
    where = config.learned_models or "segment.learned_models"

    def read() -> ModelSet:  # the learned method's only
        files = unpack_models(given.load(), source=where)
        return model_set(files, modality, config.learned_cnn, source=where)

    return read
