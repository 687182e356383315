"""Adapter of the training-rows stage: one labelled patient as the learned model's rows.

It runs after the pipeline's ingest-scan, preprocess and detect-abnormal
stages of the same patient (whose cached results it shares with ``run`` and
``cohort``), computes the robust method's mask of the slices as the learned
method does at inference (the model's prior), the features, and samples the
rows (:func:`tumor3d.learned.rows.patient_rows`). The reference arrives as a
mask artifact on its own grid (the flow reads it, emulated like the image
where the row asks for it) and is sampled here on the scan's grid. The rows
are stored as a plain ``.npz`` (:func:`tumor3d.learned.rows.rows_to_bytes`),
never pickled.
"""

from __future__ import annotations

import numpy as np

from tumor3d.config import SegmentConfig
from tumor3d.errors import InputError
from tumor3d.evaluation.grids import resample_nearest
from tumor3d.learned.rows import patient_rows, rows_to_bytes
from tumor3d.segmentation.lesion import left_right_axis
from tumor3d.segmentation.segment import learned_prior
from tumor3d.storage.objectstore import open_store
from tumor3d.storage.store import ArtifactRef
from tumor3d.tasks.segment import load_detection
from tumor3d.tasks.spec import StageOutput, StageSpec, scan_spacing_mm, stage_task

__all__ = ["SPEC", "training_rows_task"]

_XYZ_TO_ZYX = [2, 1, 0, 3]


def _zyx_affine(affine_xyz: np.ndarray) -> np.ndarray:
    """A stored volume's affine (``(x, y, z)`` indices) for its ``(z, y, x)`` array."""
    return np.asarray(affine_xyz, dtype=float)[:, _XYZ_TO_ZYX]


@stage_task("training-rows")
def training_rows_task(
    scan: ArtifactRef,
    enhanced: ArtifactRef,
    brain_mask: ArtifactRef,
    detection: ArtifactRef,
    lesion: ArtifactRef,
    head_exterior: ArtifactRef,
    reference: ArtifactRef,
    config: SegmentConfig,
    store_root: str,
) -> StageOutput:
    """The patient's training rows: features with the robust prior, sampled around the label."""
    store = open_store(store_root)
    image, scan_affine = store.get_volume(scan)
    enhanced_img, affine = store.get_volume(enhanced)
    brain, _ = store.get_volume(brain_mask)
    exterior = store.get_volume(head_exterior)[0].astype(bool)
    ref, ref_affine = store.get_volume(reference)
    label = resample_nearest(
        ref, _zyx_affine(ref_affine), image.shape, _zyx_affine(scan_affine)
    ).astype(bool)
    if reference.metadata.get("tumor_free") is not True and not label.any():
        raise InputError(  # the flow names the patient (a scan artifact holds no id)
            "the reference has no tumour on the slices of the image "
            "(does it cover the same part of the head?)"
        )
    det, meta = load_detection(store, detection, lesion)
    modality = scan.metadata["modality"]
    spacing_mm = scan_spacing_mm(scan)
    lr_axis = left_right_axis(affine)
    # the prior exactly as the learned method computes it at inference
    prior = learned_prior(
        enhanced_img,
        brain,
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
    ref_out = store.put_bytes(
        rows_to_bytes(rows),
        kind="training-rows",
        suffix=".npz",
        metadata={"n_rows": int(rows.y.size), "n_features": int(rows.x.shape[1])},
    )
    return StageOutput(
        stage="training-rows",
        artifacts={"rows": ref_out},
        values={
            "modality": modality,
            "n_rows": int(rows.y.size),
            "n_lesion_rows": int(rows.y.sum()),
            "reference_voxels": int(label.sum()),
            "prior_voxels": int(prior.sum()),
        },
    )


SPEC = StageSpec(
    name="training-rows",
    task=training_rows_task,
    entry=patient_rows,
    config_model=SegmentConfig,
    inputs={
        "scan": "scan",
        "enhanced": "image",
        "brain_mask": "mask",
        "detection": "table",
        "lesion": "mask",
        "head_exterior": "mask",
        "reference": "mask",
    },
    outputs={"rows": "training-rows"},
)
