"""Adapter of the interpolate-slices stage (spec section 4)."""

from __future__ import annotations

import numpy as np

from tumor3d.config import InterpolateConfig
from tumor3d.geometry.interpolate import interpolate_stack
from tumor3d.storage.objectstore import open_store
from tumor3d.storage.store import ArtifactRef
from tumor3d.tasks.spec import StageOutput, StageSpec, stage_task

__all__ = ["SPEC", "interpolate_task"]


@stage_task("interpolate-slices")
def interpolate_task(
    scan: ArtifactRef, tumor_mask_slices: ArtifactRef, config: InterpolateConfig, store_root: str
) -> StageOutput:
    """Shape-based interpolation of the missing slices.

    ``slices_between=None`` (automatic, [A10]) is resolved by the core from
    the scan's slice step and pixel spacing.
    """
    store = open_store(store_root)
    masks, affine = store.get_volume(tumor_mask_slices)
    stack = interpolate_stack(
        masks,
        **config.model_dump(),
        slice_step_mm=scan.metadata["slice_step_mm"],
        pixel_spacing_mm=tuple(scan.metadata["pixel_spacing_mm"]),
    )
    fine_affine = stack.fine_affine(affine)
    return StageOutput(
        stage="interpolate-slices",
        artifacts={"tumor_mask": store.put_volume(stack.mask, fine_affine, kind="mask")},
        values={
            "slices_between": int(stack.slices_between),
            "n_fine_slices": int(stack.mask.shape[0]),
            "n_interpolated_slices": int(np.count_nonzero(stack.interpolated)),
        },
    )


SPEC = StageSpec(
    name="interpolate-slices",
    task=interpolate_task,
    entry=interpolate_stack,
    config_model=InterpolateConfig,
    inputs={"scan": "scan", "tumor_mask_slices": "mask"},
    outputs={"tumor_mask": "mask"},
)
