"""Adapter of the interpolate-slices stage (spec section 4)."""

from __future__ import annotations

import numpy as np

from tumor3d.config import InterpolateConfig
from tumor3d.geometry.interpolate import interpolate_stack
from tumor3d.tasks.kinds import Artifact, Volume
from tumor3d.tasks.spec import Input, Metric, StageResult, stage

__all__ = ["SPEC"]


@stage(
    "interpolate-slices",
    entry=interpolate_stack,
    config=InterpolateConfig,
    inputs={
        "scan": Input("scan", "ingest-scan.scan", load=False),  # its slice geometry
        "tumor_mask_slices": Input("mask", "segment-tumor.tumor_mask_slices"),
    },
    outputs={"tumor_mask": "mask"},
    metrics={
        "slices_between": Metric("slices_between", "slices interpolated between two acquired"),
    },
)
def interpolate_slices(
    scan: Artifact, tumor_mask_slices: Volume, config: InterpolateConfig
) -> StageResult:
    """Shape-based interpolation of the missing slices.

    ``slices_between=None`` (automatic, [A10]) is resolved by the core from
    the scan's slice step and pixel spacing.
    """
    stack = interpolate_stack(
        tumor_mask_slices.array,
        **config.model_dump(),
        slice_step_mm=scan.metadata["slice_step_mm"],
        pixel_spacing_mm=tuple(scan.metadata["pixel_spacing_mm"]),
    )
    fine_affine = stack.fine_affine(tumor_mask_slices.affine)
    return StageResult(
        artifacts={"tumor_mask": Volume(stack.mask, fine_affine)},
        values={
            "slices_between": int(stack.slices_between),
            "n_fine_slices": int(stack.mask.shape[0]),
            "n_interpolated_slices": int(np.count_nonzero(stack.interpolated)),
        },
    )


SPEC = interpolate_slices
