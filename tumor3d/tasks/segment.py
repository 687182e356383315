"""Adapter of the segment-tumor stage (spec section 3).

The robust method reuses the lesion model of the detect stage (its
``lesion`` artifact: mask and scalars); when the detection did not compute
it (histogram detection), the model is computed here with the parameters
that artifact records (``detect.lesion``).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pandas as pd

from tumor3d.config import SegmentConfig
from tumor3d.learned.shipped import CNN_MODELS, learned_models, model_family, model_file
from tumor3d.segmentation.detect import SliceDetection
from tumor3d.segmentation.given_segmentation import given_definition, given_segmentation
from tumor3d.segmentation.lesion import LesionResult, MirrorPlane, NormalModel, left_right_axis
from tumor3d.segmentation.methods import method_spec, method_uses_lesion, slices_flagged
from tumor3d.segmentation.segment import (
    SegmentationResult,
    lesion_definition,
    resolve_method,
    segment_tumor,
)
from tumor3d.storage.nifti import probability_for_storage
from tumor3d.tasks.kinds import Artifact, Volume
from tumor3d.tasks.spec import Input, Metric, StageResult, scan_spacing_mm, stage

__all__ = ["SPEC", "lesion_from_artifact", "load_detection"]


def _f(v: Any, missing: float = float("nan")) -> float:
    return missing if v is None else float(v)


def _json_float(v: float) -> float | None:
    """A figure as JSON allows it (None for inf and NaN)."""
    v = float(v)
    return v if np.isfinite(v) else None


def lesion_from_artifact(mask: np.ndarray, meta: dict[str, Any]) -> LesionResult | None:
    """The :class:`LesionResult` stored by the detect stage; None if it was not computed."""
    if not meta.get("computed"):
        return None
    model = NormalModel(
        _f(meta["median"]),
        _f(meta["sigma"]),
        _f(meta["seed_threshold"]),
        _f(meta["csf_threshold"], float("inf")),
    )
    plane = meta.get("mirror_plane")
    return LesionResult(
        np.asarray(mask, dtype=bool),
        model,
        _f(meta["lesion_gray"]),
        _f(meta["grow_threshold"]),
        int(meta["n_components"]),
        None
        if plane is None
        else MirrorPlane(int(plane["lr_axis"]), float(plane["yaw_deg"]), float(plane["offset_mm"])),
        bool(meta.get("midline", False)),  # absent from artifacts written before step 3f
    )


def load_detection(
    detection: pd.DataFrame, lesion: Artifact, *, with_lesion: bool = True
) -> tuple[SliceDetection, dict[str, Any]]:
    """The detect stage's :class:`SliceDetection` and its lesion artifact's metadata.

    With ``with_lesion``, the lesion model it computed (if it did) is put back
    on the detection, so the robust method does not compute it again.
    """
    det = SliceDetection.from_records(detection.to_dict("records"))
    meta = lesion.metadata["lesion"]
    if with_lesion and meta.get("computed"):
        det = dataclasses.replace(det, lesion=lesion_from_artifact(lesion.load().array, meta))
    return det, meta


def _records(result: SegmentationResult, detected: Any) -> list[dict[str, Any]]:
    """The per-slice table: :meth:`SegmentationResult.to_records` and ``flagged``.

    ``flagged``: the slices the method flags abnormal
    (:func:`tumor3d.segmentation.methods.slices_flagged`: the detection's for a
    method that segments those, else the slices with tumour).
    """
    flags = slices_flagged(result.method, detected, result.tumor_pixels)
    return [{**r, "flagged": bool(f)} for r, f in zip(result.to_records(), flags, strict=True)]


@stage(
    "segment-tumor",
    entry=segment_tumor,
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
) -> StageResult:
    """Tumour segmentation: the lesion model (robust), wavelet + histogram FCM, or the peer.

    ``given_mask``, the user's segmentation on the scan's grid (``--segmentation``,
    its file name in the artifact's ``given_file``), replaces the method: stored as
    is, method ``"given"``; as an input artifact its content enters the cache key.
    """
    if given_mask is not None:
        mask, mask_affine = given_mask.load()
        res = given_segmentation(mask.astype(bool), spacing_mm=scan_spacing_mm(scan))
        name = given_mask.metadata.get("given_file")
        return StageResult(
            artifacts={
                "tumor_mask_slices": Volume(res.tumor_mask, mask_affine),
                "segmentation": _records(res, detection["abnormal"]),
            },
            values={
                "tumor_pixels_total": int(np.sum(res.tumor_pixels)),
                "n_tumor_slices": int(np.count_nonzero(res.tumor_pixels)),
                "caveats": list(res.caveats),
                "modality": scan.metadata["modality"],
                "segment_method": res.method,
                "measured": given_definition(name),
                "segment_model": "",
            },
        )
    image, affine = enhanced
    exterior = head_exterior.array.astype(bool)
    det, meta = load_detection(detection, lesion, with_lesion=method_uses_lesion(config.method))
    modality = scan.metadata["modality"]
    learned: dict[str, Any] = {}
    if method_spec(resolve_method(config.method, modality, det)).needs_model:  # image + model
        # segment.learned_cnn auto: with the shipped U-Net of the sequence, if any (FLAIR)
        learned = {"image": scan.load().array, **learned_models(modality, config.learned_cnn)}
    result = segment_tumor(
        image,
        brain_mask.array,
        det,
        modality=modality,
        spacing_mm=scan_spacing_mm(scan),
        lr_axis=left_right_axis(affine),
        lesion=meta["params"],
        # the air outside a raw head (none stored for a skull-stripped one): scalp caveat
        head_exterior=exterior if exterior.any() else None,
        **config.model_dump(),
        **learned,
    )
    artifacts: dict[str, Any] = {
        "tumor_mask_slices": Volume(result.tumor_mask, affine),
        "segmentation": _records(result, det.abnormal),
    }
    review: dict[str, Any] = {}
    if result.probability is not None:
        artifacts["tumor_probability"] = Volume(probability_for_storage(result.probability), affine)
    cnn = learned.get("cnn") if result.method == "learned" else None
    segment_model = (
        "" if result.method != "learned" else ("forest" if cnn is None else "forest + U-Net mean")
    )
    if result.review is not None:  # read by tumor3d.segmentation.review.review_status
        review = {
            "needs_review": bool(result.review.needs_review),
            "review_reasons": list(result.review.reasons),
            "quality_score": float(result.review.quality_score),
            "review_figures": {k: _json_float(v) for k, v in result.review.figures.items()},
            "model": learned["model"].meta.get("name", "shipped"),
            # of its file, as training.json and sha256sum give it (a model in memory: of
            # its arrays and metadata)
            "model_file": model_file(model_family(modality)),
            "model_sha256": learned["model"].file_sha256 or learned["model"].digest(),
        }
        if cnn is not None:  # the U-Nets averaged with the forest: their files and SHA-256s
            review.update(
                cnn_model=list(CNN_MODELS[modality.lower()]),  # in cnn_sha256's order
                cnn_sha256=[n.sha256 for n in cnn],
            )
    return StageResult(
        artifacts=artifacts,
        values={
            **review,
            "tumor_pixels_total": int(np.sum(result.tumor_pixels)),
            "n_tumor_slices": int(np.count_nonzero(result.tumor_pixels)),
            # where the volume may be wrong, in words (the run's notes say them)
            "caveats": list(result.caveats),
            # which method ran and what its mask (every volume) holds, in words
            "modality": modality,
            "segment_method": result.method,
            "measured": lesion_definition(result.method, modality),
            "segment_model": segment_model,
        },
    )


SPEC = segment
