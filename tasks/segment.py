"""Adapter of the segment-tumor stage (spec section 3)."""

from __future__ import annotations

import numpy as np

from storage.objectstore import open_store
from storage.store import ArtifactRef
from tasks.spec import StageOutput, StageSpec, stage_task
from tumor3d.config import SegmentConfig
from tumor3d.detect import SliceDetection
from tumor3d.lesion import left_right_axis
from tumor3d.segment import segment_tumor

__all__ = ["SPEC", "segment_task"]


def _spacing(scan: ArtifactRef) -> tuple[float, float, float]:
    """(slice step, row, column) voxel spacing in mm from the scan's metadata."""
    dy, dx = scan.metadata["pixel_spacing_mm"]
    return (float(scan.metadata["slice_step_mm"]), float(dy), float(dx))


@stage_task("segment-tumor")
def segment_task(
    scan: ArtifactRef,
    enhanced: ArtifactRef,
    brain_mask: ArtifactRef,
    detection: ArtifactRef,
    config: SegmentConfig,
    store_root: str,
) -> StageOutput:
    """Wavelet + histogram fuzzy c-means tumour segmentation."""
    store = open_store(store_root)
    image, affine = store.get_volume(enhanced)
    brain, _ = store.get_volume(brain_mask)
    det = SliceDetection.from_records(store.get_table(detection).to_dict("records"))
    result = segment_tumor(
        image,
        brain,
        det,
        modality=scan.metadata["modality"],
        spacing_mm=_spacing(scan),
        lr_axis=left_right_axis(affine),
        **config.model_dump(),
    )
    return StageOutput(
        stage="segment-tumor",
        artifacts={
            "tumor_mask_slices": store.put_volume(result.tumor_mask, affine, kind="mask"),
            "segmentation": store.put_table(result.to_records()),
        },
        values={
            "tumor_pixels_total": int(np.sum(result.tumor_pixels)),
            "n_tumor_slices": int(np.count_nonzero(result.tumor_pixels)),
        },
    )


SPEC = StageSpec(
    name="segment-tumor",
    task=segment_task,
    entry=segment_tumor,
    config_model=SegmentConfig,
    inputs={"scan": "scan", "enhanced": "image", "brain_mask": "mask", "detection": "table"},
    outputs={"tumor_mask_slices": "mask", "segmentation": "table"},
)
