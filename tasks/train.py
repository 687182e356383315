"""Adapters of the training stages: one labelled patient as the learned models' rows.

``training-rows`` (:data:`SPEC`), the forest's rows:

It runs after the pipeline's ingest-scan, preprocess and detect-abnormal
stages of the same patient (whose cached results it shares with ``run`` and
``cohort``), computes the robust method's mask of the slices as the learned
method does at inference (the model's prior), the features, and samples the
rows (:func:`tumor3d.learned.rows.patient_rows`). The reference arrives as a
mask artifact on its own grid (the flow reads it, emulated like the image
where the row asks for it) and is sampled here on the scan's grid. The rows
are stored as a plain ``.npz`` (:func:`tumor3d.learned.rows.rows_to_bytes`),
never pickled.

``unet-slices`` (:data:`UNET_SLICES`), the U-Net's: the scan as acquired
and the reference on its grid, resampled to the network's input and target
slices (:func:`tumor3d.learned.cnn_train.unet_slices`, the grids inference
uses) at the shipped network's size and context
(:data:`tumor3d.learned.cnn_train.UNetSettings` defaults), stored as a plain
``.npz`` (:func:`tumor3d.learned.cnn_train.slices_to_bytes`). It needs the
ingest stage only, and no torch.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from tumor3d.config import SegmentConfig
from tumor3d.errors import InputError
from tumor3d.evaluation.grids import resample_nearest
from tumor3d.learned.cnn_train import UNetSettings, slices_to_bytes, unet_slices
from tumor3d.learned.rows import patient_rows, rows_to_bytes
from tumor3d.segmentation.lesion import left_right_axis
from tumor3d.segmentation.segment import learned_prior
from tumor3d.tasks.kinds import Artifact, Tagged, Volume
from tumor3d.tasks.segment import load_detection
from tumor3d.tasks.spec import Input, StageResult, scan_spacing_mm, stage

__all__ = ["SPEC", "UNET_SLICES"]

_XYZ_TO_ZYX = [2, 1, 0, 3]


def _zyx_affine(affine_xyz: np.ndarray) -> np.ndarray:
    """A stored volume's affine (``(x, y, z)`` indices) for its ``(z, y, x)`` array."""
    return np.asarray(affine_xyz, dtype=float)[:, _XYZ_TO_ZYX]


@stage(
    "training-rows",
    entry=patient_rows,
    config=SegmentConfig,
    inputs={
        "scan": Input("scan", "ingest-scan.scan", load=False),  # its image and geometry
        "enhanced": Input("image", "preprocess.enhanced"),
        "brain_mask": Input("mask", "preprocess.brain_mask"),
        "detection": Input("table", "detect-abnormal.detection"),
        "lesion": Input("mask", "detect-abnormal.lesion", load=False),
        "head_exterior": Input("mask", "preprocess.head_exterior"),
        # the label on its own grid, marked tumor_free or not (the training flow stores it)
        "reference": Input("mask", "given:reference", load=False),
    },
    outputs={"rows": "training-rows"},
)
def training_rows(
    scan: Artifact,
    enhanced: Volume,
    brain_mask: Volume,
    detection: pd.DataFrame,
    lesion: Artifact,
    head_exterior: Volume,
    reference: Artifact,
    config: SegmentConfig,
) -> StageResult:
    """The patient's training rows: features with the robust prior, sampled around the label."""
    image, label = _reference_on_scan(scan, reference)
    enhanced_img, affine = enhanced
    exterior = head_exterior.array.astype(bool)
    det, meta = load_detection(detection, lesion)
    modality = scan.metadata["modality"]
    spacing_mm = scan_spacing_mm(scan)
    lr_axis = left_right_axis(affine)
    # the prior exactly as the learned method computes it at inference
    prior = learned_prior(
        enhanced_img,
        brain_mask.array,
        det,
        modality=modality,
        min_tumor_pixels=config.min_tumor_pixels,
        lesion=meta["params"],
        spacing_mm=spacing_mm,
        lr_axis=lr_axis,
        head_exterior=exterior if exterior.any() else None,
    ).tumor_mask
    rows = patient_rows(
        image, label, spacing_mm=spacing_mm, modality=modality, lr_axis=lr_axis, prior=prior
    )
    counts = {"n_rows": int(rows.y.size), "n_features": int(rows.x.shape[1])}
    return StageResult(
        artifacts={"rows": Tagged(rows_to_bytes(rows), counts)},
        values={
            "modality": modality,
            "n_rows": int(rows.y.size),
            "n_lesion_rows": int(rows.y.sum()),
            "reference_voxels": int(label.sum()),
            "prior_voxels": int(prior.sum()),
        },
    )


SPEC = training_rows


def _reference_on_scan(scan: Artifact, reference: Artifact) -> tuple[np.ndarray, np.ndarray]:
    """The scan's image ``(z, y, x)`` and the reference resampled onto its grid (bool)."""
    image, scan_affine = scan.load()
    ref, ref_affine = reference.load()
    label = resample_nearest(
        ref, _zyx_affine(ref_affine), image.shape, _zyx_affine(scan_affine)
    ).astype(bool)
    if reference.metadata.get("tumor_free") is not True and not label.any():
        raise InputError(  # the flow names the patient (a scan artifact holds no id)
            "the reference has no tumour on the slices of the image "
            "(does it cover the same part of the head?)"
        )
    return image, label


@stage(
    "unet-slices",
    entry=unet_slices,
    inputs={
        "scan": Input("scan", "ingest-scan.scan", load=False),
        "reference": Input("mask", "given:reference", load=False),
    },
    outputs={"slices": "training-rows"},
)
def unet_training_slices(scan: Artifact, reference: Artifact) -> StageResult:
    """The patient's U-Net input and target slices (the shipped network's grid)."""
    image, label = _reference_on_scan(scan, reference)
    x, y = unet_slices(image, label, UNetSettings(), pixel_mm=scan_spacing_mm(scan)[1:])
    tumour = int(np.sum(y.reshape(len(y), -1).max(axis=1) > 0))
    counts = {"n_slices": int(len(x)), "n_tumour_slices": tumour}
    return StageResult(
        artifacts={"slices": Tagged(slices_to_bytes(x, y), counts)},
        values={"modality": scan.metadata["modality"], **counts},
    )


UNET_SLICES = unet_training_slices
