"""Adapter of the extract-brain-surface stage (spec section 7: the brain around the tumour).

Computed once per brain mask and cached like every stage: the renders, the
published ``brain_mesh.ply`` and ``viewer.html`` reuse it, so neither a new
render setting nor a new tumour surface recomputes it.
"""

from __future__ import annotations

from tumor3d.geometry.brain_surface import brain_surface, display_mesh
from tumor3d.pipeline import empty_mesh
from tumor3d.tasks.kinds import Volume
from tumor3d.tasks.spec import Input, StageResult, stage

__all__ = ["BRAIN_SURFACE_SPACING_MM", "VIEWER_BRAIN_MAX_FACES", "SPEC"]

#: Grid spacing of the translucent brain surface (a context surface, not a measurement).
BRAIN_SURFACE_SPACING_MM = 2.0

#: Face budget of the brain in ``viewer.html`` (the browser holds and draws it).
VIEWER_BRAIN_MAX_FACES = 8000


@stage(
    "extract-brain-surface",
    entry=brain_surface,
    inputs={"brain_mask": Input("mask", "preprocess.brain_mask")},
    outputs={"brain_mesh": "mesh", "brain_mesh_viewer": "mesh"},
)
def extract_brain_surface(brain_mask: Volume) -> StageResult:
    """The brain surface for the renders and a lighter copy for the viewer (empty if no brain)."""
    if brain_mask.array.any():
        brain = brain_surface(
            brain_mask.array, brain_mask.affine, spacing_mm=BRAIN_SURFACE_SPACING_MM
        )
        viewer = display_mesh(brain, VIEWER_BRAIN_MAX_FACES)
    else:
        brain = viewer = empty_mesh()
    return StageResult(
        artifacts={"brain_mesh": brain, "brain_mesh_viewer": viewer},
        values={"faces": brain.n_faces, "faces_viewer": viewer.n_faces},
    )


SPEC = extract_brain_surface
