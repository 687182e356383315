"""Adapter of the preprocess stage (spec section 1)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from tumor3d.config import PreprocessConfig
from tumor3d.imaging.preprocess import (
    brain_coverage_note,
    brain_size_note,
    brain_volume_note,
    preprocess_volume,
    tissue_slice_count,
)
from tumor3d.tasks.kinds import Artifact, Volume
from tumor3d.tasks.spec import Input, StageResult, scan_spacing_mm, stage

__all__ = ["SPEC", "preprocess_notes", "skull_removal_notes", "voxel_size_notes"]


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
    brain_voxels = int(np.count_nonzero(result.brain_mask))
    per_slice = np.count_nonzero(result.brain_mask, axis=(1, 2))
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
        values={
            "brain_voxels": brain_voxels,
            "brain_volume_ml": brain_voxels * float(np.prod(spacing)) / 1000.0,
            "brain_extraction": result.brain_extraction,
            "brain_slices": int(np.count_nonzero(per_slice)),
            "brain_max_slice_mm2": float(per_slice.max()) * float(spacing[1]) * float(spacing[2]),
            "tissue_slices": tissue_slice_count(result.original_u8),
        },
    )


def preprocess_notes(values: Mapping[str, Any]) -> list[str]:
    """The run's notes on the brain mask, from the preprocess stage's values.

    A mask larger than any skull holds (:func:`tumor3d.imaging.preprocess.brain_volume_note`),
    smaller than any human brain (:func:`tumor3d.imaging.preprocess.brain_size_note`, a given
    mask too: a wrong voxel size in the header shrinks it as well), or found on too
    few of the slices that hold tissue
    (:func:`tumor3d.imaging.preprocess.brain_coverage_note`; not for a given mask, which is
    the user's). Values without the slice counts give no coverage note; the stage
    always stores them, and its code enters its cache key, so none reach here from
    an older cache. (A run says them as :func:`skull_removal_notes` then
    :func:`voxel_size_notes`.)
    """
    return [n for n in _notes(values) if n]


def skull_removal_notes(values: Mapping[str, Any], *, doubts_result: bool = True) -> list[str]:
    """Those of :func:`preprocess_notes` on the skull removal (volume, coverage).

    They doubt a tumour segmented inside the brain mask; ``doubts_result`` False
    (a method that reads the whole head) words them for that
    (:func:`tumor3d.imaging.preprocess.brain_volume_note`).
    """
    volume, _, coverage = _notes(values, doubts_result)
    return [n for n in (volume, coverage) if n]


def voxel_size_notes(values: Mapping[str, Any]) -> list[str]:
    """The one of :func:`preprocess_notes` that doubts the header's voxel size.

    A brain too small to be human: it doubts every volume, whatever the method.
    """
    return [n for n in _notes(values)[1:2] if n]


def _notes(
    values: Mapping[str, Any], doubts_result: bool = True
) -> tuple[str | None, str | None, str | None]:
    volume = brain_volume_note(values.get("brain_volume_ml", 0.0), doubts_result=doubts_result)
    size = None
    if "brain_max_slice_mm2" in values:  # a mask of the user's too: theirs may be off
        size = brain_size_note(values["brain_max_slice_mm2"])
    coverage = None
    if values.get("brain_extraction") != "given":
        slices = (values.get("brain_slices", 0), values.get("tissue_slices", 0))
        coverage = brain_coverage_note(
            *slices, values.get("brain_extraction", ""), doubts_result=doubts_result
        )
    return volume, size, coverage


SPEC = preprocess
