"""Adapter of the extract-surface stage (spec section 5)."""

from __future__ import annotations

from tumor3d.config import SurfaceConfig
from tumor3d.pipeline import is_closed_surface, tumour_surface
from tumor3d.storage.objectstore import open_store
from tumor3d.storage.store import ArtifactRef
from tumor3d.tasks.spec import StageOutput, StageSpec, stage_task

__all__ = ["SPEC", "surface_task"]


@stage_task("extract-surface")
def surface_task(tumor_mask: ArtifactRef, config: SurfaceConfig, store_root: str) -> StageOutput:
    """Marching cubes on the zero-padded interpolated mask (empty mesh when no tumour)."""
    store = open_store(store_root)
    mask, affine = store.get_volume(tumor_mask)
    mesh = tumour_surface(mask, affine, **config.model_dump())
    return StageOutput(
        stage="extract-surface",
        artifacts={"mesh": store.put_mesh(mesh)},
        values={
            "faces": mesh.n_faces,
            "vertices": mesh.n_vertices,
            "watertight": is_closed_surface(mesh),
        },
    )


SPEC = StageSpec(
    name="extract-surface",
    task=surface_task,
    entry=tumour_surface,
    config_model=SurfaceConfig,
    inputs={"tumor_mask": "mask"},
    outputs={"mesh": "mesh"},
)
