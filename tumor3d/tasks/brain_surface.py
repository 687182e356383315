"""Adapter of the extract-brain-surface stage (spec section 7: the brain around the tumour).

Computed once per brain mask and cached like every stage: the renders, the
published ``brain_mesh.ply`` and ``viewer.html`` reuse it, so neither a new
render setting nor a new tumour surface recomputes it.
"""

from __future__ import annotations

from tumor3d.geometry.brain_surface import brain_surface, display_mesh
from tumor3d.pipeline import empty_mesh
from tumor3d.storage.objectstore import open_store
from tumor3d.storage.store import ArtifactRef
from tumor3d.tasks.spec import StageOutput, StageSpec, stage_task

__all__ = ["BRAIN_SURFACE_SPACING_MM", "VIEWER_BRAIN_MAX_FACES", "SPEC", "brain_surface_task"]

#: Grid spacing of the translucent brain surface (a context surface, not a measurement).
BRAIN_SURFACE_SPACING_MM = 2.0

#: Face budget of the brain in ``viewer.html`` (the browser holds and draws it).
VIEWER_BRAIN_MAX_FACES = 8000


@stage_task("extract-brain-surface")
def brain_surface_task(brain_mask: ArtifactRef, store_root: str) -> StageOutput:
    """The brain surface for the renders and a lighter copy for the viewer (empty if no brain)."""
    store = open_store(store_root)
    mask, affine = store.get_volume(brain_mask)
    if mask.any():
        brain = brain_surface(mask, affine, spacing_mm=BRAIN_SURFACE_SPACING_MM)
        viewer = display_mesh(brain, VIEWER_BRAIN_MAX_FACES)
    else:
        brain = viewer = empty_mesh()
    return StageOutput(
        stage="extract-brain-surface",
        artifacts={
            "brain_mesh": store.put_mesh(brain),
            "brain_mesh_viewer": store.put_mesh(viewer),
        },
        values={"faces": brain.n_faces, "faces_viewer": viewer.n_faces},
    )


SPEC = StageSpec(
    name="extract-brain-surface",
    task=brain_surface_task,
    entry=brain_surface,
    config_model=None,
    inputs={"brain_mask": "mask"},
    outputs={"brain_mesh": "mesh", "brain_mesh_viewer": "mesh"},
)
