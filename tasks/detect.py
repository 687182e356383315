"""Adapter of the detect-abnormal stage (spec section 2).

The robust detection computes the patient lesion model
(:func:`tumor3d.segmentation.lesion.segment_hyperintense_lesion`); its mask and scalars
are stored as the ``lesion`` artifact, which the segment stage reuses (the
model runs once per patient). Without the robust detection the artifact
holds an empty mask marked ``computed: false`` and the lesion parameters,
so that a robust segmentation computes the model itself.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from tumor3d.config import DetectConfig
from tumor3d.segmentation.detect import detect_abnormal_slices
from tumor3d.segmentation.lesion import LesionResult, left_right_axis
from tumor3d.tasks.kinds import Artifact, Tagged, Volume
from tumor3d.tasks.spec import Input, StageResult, scan_spacing_mm, stage

__all__ = ["SPEC", "lesion_metadata"]


def _num(v: float) -> float | None:
    """JSON-able float: None for NaN and infinities."""
    return float(v) if math.isfinite(float(v)) else None


def lesion_metadata(lesion: LesionResult | None, params: dict[str, Any]) -> dict[str, Any]:
    """The ``lesion`` artifact's metadata: whether it was computed, its scalars, its params."""
    meta: dict[str, Any] = {"computed": lesion is not None, "params": dict(params)}
    if lesion is not None:
        m = lesion.model
        meta.update(
            median=_num(m.median),
            sigma=_num(m.sigma),
            seed_threshold=_num(m.seed_threshold),
            csf_threshold=_num(m.csf_threshold),
            lesion_gray=_num(lesion.lesion_gray),
            grow_threshold=_num(lesion.grow_threshold),
            n_components=int(lesion.n_components),
            midline=bool(lesion.midline),
            mirror_plane=None
            if lesion.plane is None
            else {
                "lr_axis": int(lesion.plane.axis),
                "yaw_deg": float(lesion.plane.yaw_deg),
                "offset_mm": float(lesion.plane.offset_mm),
            },
        )
    return meta


@stage(
    "detect-abnormal",
    entry=detect_abnormal_slices,
    config=DetectConfig,
    inputs={
        "scan": Input("scan", "ingest-scan.scan", load=False),  # modality and spacing
        "enhanced": Input("image", "preprocess.enhanced"),
        "brain_mask": Input("mask", "preprocess.brain_mask"),
    },
    outputs={"detection": "table", "lesion": "mask"},
)
def detect_abnormal(
    scan: Artifact, enhanced: Volume, brain_mask: Volume, config: DetectConfig
) -> StageResult:
    """Abnormal-slice detection (histogram modes, or the patient's lesion model)."""
    image, affine = enhanced
    detection = detect_abnormal_slices(
        image,
        brain_mask.array,
        modality=scan.metadata["modality"],
        spacing_mm=scan_spacing_mm(scan),
        lr_axis=left_right_axis(affine),
        **config.model_dump(),
    )
    abnormal = np.flatnonzero(detection.abnormal)
    lesion = detection.lesion
    mask = lesion.mask if lesion is not None else np.zeros(image.shape, dtype=bool)
    meta = lesion_metadata(lesion, config.lesion.model_dump())
    return StageResult(
        artifacts={
            "detection": detection.to_records(),
            "lesion": Tagged(Volume(mask, affine), {"lesion": meta}),
        },
        values={
            "n_abnormal_slices": int(abnormal.size),
            "abnormal_slices": abnormal.tolist(),
            "lesion_computed": lesion is not None,
        },
    )


SPEC = detect_abnormal
