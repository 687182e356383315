"""Adapter of the simplify-mesh stage (spec section 6)."""

from __future__ import annotations

from typing import Any

from tumor3d.config import SimplifyConfig
from tumor3d.geometry.mesh import Mesh
from tumor3d.pipeline import is_closed_surface
from tumor3d.simplify import simplify_mesh, target_face_count
from tumor3d.tasks.spec import Input, Metric, StageResult, stage

__all__ = ["SPEC"]

#: The smallest closed triangle mesh (a tetrahedron) has 4 faces.
_MIN_SIMPLIFIED_FACES = 4


@stage(
    "simplify-mesh",
    entry=simplify_mesh,
    config=SimplifyConfig,
    inputs={"mesh": Input("mesh", "extract-surface.mesh")},
    outputs={"mesh": "mesh"},
    metrics={
        "faces_simplified": Metric("faces", "faces of the simplified surface"),
        "faces_target": Metric("faces_target", "F_target, the simplification's face budget"),
        "mesh_simplified_watertight": Metric("watertight", "the simplified surface is closed"),
    },
)
def simplify_surface(mesh: Mesh, config: SimplifyConfig) -> StageResult:
    """Edge-collapse simplification to F_target faces.

    A mesh too small to simplify (F_target below 4 faces) is passed through
    unchanged and flagged, rather than failing the patient.
    """
    target = target_face_count(mesh.n_faces, config.reduction_percent)
    values: dict[str, Any] = {"faces_target": target, "simplified": False}
    simplified = mesh
    if not mesh.is_empty and target >= _MIN_SIMPLIFIED_FACES:
        simplified, info = simplify_mesh(mesh, **config.model_dump(), return_info=True)
        values.update(simplified=True, watertight=bool(info["watertight"]))
    else:
        values["watertight"] = is_closed_surface(mesh)
    values["faces"] = simplified.n_faces
    return StageResult(artifacts={"mesh": simplified}, values=values)


SPEC = simplify_surface
