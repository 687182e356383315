"""Adapter of the simplify-mesh stage (spec section 6)."""

from __future__ import annotations

from typing import Any

from tumor3d.config import SimplifyConfig
from tumor3d.pipeline import is_closed_surface
from tumor3d.simplify import simplify_mesh, target_face_count
from tumor3d.storage.objectstore import open_store
from tumor3d.storage.store import ArtifactRef
from tumor3d.tasks.spec import StageOutput, StageSpec, stage_task

__all__ = ["SPEC", "simplify_task"]

#: The smallest closed triangle mesh (a tetrahedron) has 4 faces.
_MIN_SIMPLIFIED_FACES = 4


@stage_task("simplify-mesh")
def simplify_task(mesh: ArtifactRef, config: SimplifyConfig, store_root: str) -> StageOutput:
    """Edge-collapse simplification to F_target faces.

    A mesh too small to simplify (F_target below 4 faces) is passed through
    unchanged and flagged, rather than failing the patient.
    """
    store = open_store(store_root)
    source = store.get_mesh(mesh)
    target = target_face_count(source.n_faces, config.reduction_percent)
    values: dict[str, Any] = {"faces_target": target, "simplified": False}
    simplified = source
    if not source.is_empty and target >= _MIN_SIMPLIFIED_FACES:
        simplified, info = simplify_mesh(source, **config.model_dump(), return_info=True)
        values.update(simplified=True, watertight=bool(info["watertight"]))
    else:
        values["watertight"] = is_closed_surface(source)
    values["faces"] = simplified.n_faces
    return StageOutput(
        stage="simplify-mesh", artifacts={"mesh": store.put_mesh(simplified)}, values=values
    )


SPEC = StageSpec(
    name="simplify-mesh",
    task=simplify_task,
    entry=simplify_mesh,
    config_model=SimplifyConfig,
    inputs={"mesh": "mesh"},
    outputs={"mesh": "mesh"},
)
