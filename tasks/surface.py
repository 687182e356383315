"""Adapter of the extract-surface stage (spec section 5)."""

from __future__ import annotations

from tumor3d.config import SurfaceConfig
from tumor3d.pipeline import is_closed_surface, tumour_surface
from tumor3d.tasks.kinds import Volume
from tumor3d.tasks.spec import Input, Metric, StageResult, stage

__all__ = ["SPEC"]


@stage(
    "extract-surface",
    entry=tumour_surface,
    config=SurfaceConfig,
    inputs={"tumor_mask": Input("mask", "interpolate-slices.tumor_mask")},
    outputs={"mesh": "mesh"},
    metrics={
        "faces_mc": Metric("faces", "faces of the marching-cubes surface"),
        "mesh_watertight": Metric("watertight", "the marching-cubes surface is closed"),
    },
)
def extract_surface(tumor_mask: Volume, config: SurfaceConfig) -> StageResult:
    """Marching cubes on the zero-padded interpolated mask (empty mesh when no tumour)."""
    mesh = tumour_surface(tumor_mask.array, tumor_mask.affine, **config.model_dump())
    return StageResult(
        artifacts={"mesh": mesh},
        values={
            "faces": mesh.n_faces,
            "vertices": mesh.n_vertices,
            "watertight": is_closed_surface(mesh),
        },
    )


SPEC = extract_surface
