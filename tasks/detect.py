"""Adapter of the detect-abnormal stage (spec section 2)."""

from __future__ import annotations

import numpy as np

from storage.objectstore import open_store
from storage.store import ArtifactRef
from tasks.spec import StageOutput, StageSpec, stage_task
from tumor3d.config import DetectConfig
from tumor3d.detect import detect_abnormal_slices
from tumor3d.lesion import left_right_axis

__all__ = ["SPEC", "detect_task"]


def _spacing(scan: ArtifactRef) -> tuple[float, float, float]:
    """(slice step, row, column) voxel spacing in mm from the scan's metadata."""
    dy, dx = scan.metadata["pixel_spacing_mm"]
    return (float(scan.metadata["slice_step_mm"]), float(dy), float(dx))


@stage_task("detect-abnormal")
def detect_task(
    scan: ArtifactRef,
    enhanced: ArtifactRef,
    brain_mask: ArtifactRef,
    config: DetectConfig,
    store_root: str,
) -> StageOutput:
    """Abnormal-slice detection (histogram modes, or the patient's lesion model)."""
    store = open_store(store_root)
    image, affine = store.get_volume(enhanced)
    brain, _ = store.get_volume(brain_mask)
    detection = detect_abnormal_slices(
        image,
        brain,
        modality=scan.metadata["modality"],
        spacing_mm=_spacing(scan),
        lr_axis=left_right_axis(affine),
        **config.model_dump(),
    )
    abnormal = np.flatnonzero(detection.abnormal)
    return StageOutput(
        stage="detect-abnormal",
        artifacts={"detection": store.put_table(detection.to_records())},
        values={"n_abnormal_slices": int(abnormal.size), "abnormal_slices": abnormal.tolist()},
    )


SPEC = StageSpec(
    name="detect-abnormal",
    task=detect_task,
    entry=detect_abnormal_slices,
    config_model=DetectConfig,
    inputs={"scan": "scan", "enhanced": "image", "brain_mask": "mask"},
    outputs={"detection": "table"},
)
