"""Adapter of the preprocess stage (spec section 1)."""

from __future__ import annotations

import numpy as np

from tumor3d.config import PreprocessConfig
from tumor3d.imaging.preprocess import brain_mask_figures, preprocess_volume
from tumor3d.tasks.kinds import Artifact, Volume
from tumor3d.tasks.spec import Input, Metric, StageResult, scan_spacing_mm, stage

__all__ = ["SPEC"]


@stage(
    "preprocess",
    entry=preprocess_volume,
    config=PreprocessConfig,
    inputs={
        "scan": Input("scan", "ingest-scan.scan", load=False),  # its image and spacing
        # a given mask on the scan's grid (--brain-mask, the manifest's brain_mask)
        "brain_mask": Input("mask", "given:brain_mask", optional=True),
    },
    outputs={"enhanced": "image", "brain_mask": "mask", "head_exterior": "mask"},
    metrics={
        "brain_volume_ml": Metric("brain_volume_ml", "the brain mask's volume, mL"),
        "outline_shift_mm": Metric(
            "outline_shift_mm",
            "median change of the head's circle-equivalent radius from slice to slice, mm "
            "(empty: no verdict); above one slice step the header's step is doubted",
        ),
    },
)
def preprocess(
    scan: Artifact, config: PreprocessConfig, brain_mask: Volume | None = None
) -> StageResult:
    """Median, unsharp masking, equalisation and skull removal.

    ``brain_mask``, a given mask on the scan's grid (``--brain-mask``, the
    manifest's ``brain_mask``), replaces the skull removal; as an input
    artifact, its content enters the cache key.
    """
    image, affine = scan.load()
    given = None if brain_mask is None else brain_mask.array
    spacing = scan_spacing_mm(scan)
    result = preprocess_volume(image, **config.model_dump(), spacing_mm=spacing, brain_mask=given)
    # the air outside a raw head; all False when there is none (skull-stripped, given)
    exterior = result.head_exterior
    if exterior is None:
        exterior = np.zeros(result.brain_mask.shape, dtype=bool)
    return StageResult(
        artifacts={
            "enhanced": Volume(result.enhanced, affine, dtype="uint8"),
            "brain_mask": Volume(result.brain_mask, affine),
            "head_exterior": Volume(exterior, affine),
        },
        values=brain_mask_figures(
            result.brain_mask, spacing, result.brain_extraction, result.original_u8
        ),
    )


SPEC = preprocess
