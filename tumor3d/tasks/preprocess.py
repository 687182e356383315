"""Adapter of the preprocess stage (spec section 1)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from tumor3d.config import PreprocessConfig
from tumor3d.imaging.preprocess import (
    brain_mask_figures,
    brain_mask_notes,
    preprocess_volume,
    tissue_slice_count,
)
from tumor3d.tasks.kinds import Artifact, Volume
from tumor3d.tasks.spec import Input, StageResult, scan_spacing_mm, stage

__all__ = ["SPEC", "preprocess_notes"]


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
            result.brain_mask,
            spacing,
            result.brain_extraction,
            tissue_slice_count(result.original_u8),
        ),
    )


def preprocess_notes(values: Mapping[str, Any]) -> list[str]:
    """The run's notes on the brain mask, from the preprocess stage's values.

    A mask larger than any skull holds (:func:`tumor3d.imaging.preprocess.brain_volume_note`),
    found on too few of the slices that hold tissue
    (:func:`tumor3d.imaging.preprocess.brain_coverage_note`; not for a given mask, which is
    the user's), or smaller than any human brain
    (:func:`tumor3d.imaging.preprocess.brain_size_note`, a given mask too: a wrong voxel size
    in the header shrinks it as well): :func:`tumor3d.imaging.preprocess.brain_mask_notes`,
    in a run's order. Values without the slice counts give no coverage note; the stage
    always stores them, and its code enters its cache key, so none reach here from
    an older cache.
    """
    skull, size = brain_mask_notes(values)
    return skull + size


SPEC = preprocess
