"""Adapter of the render-views stage (spec section 7)."""

from __future__ import annotations

from typing import Any

from tumor3d.config import RenderConfig
from tumor3d.geometry.mesh import Mesh
from tumor3d.tasks.kinds import Artifact, Tagged
from tumor3d.tasks.spec import Input, StageResult, stage
from tumor3d.visual.render import render_views, turntable_gif

__all__ = ["SPEC"]


@stage(
    "render-views",
    entry=render_views,
    config=RenderConfig,
    inputs={
        "mesh": Input("mesh", "simplify-mesh.mesh"),
        # loaded only when there is a tumour to render
        "brain_mesh": Input("mesh", "extract-brain-surface.brain_mesh", load=False),
    },
    outputs={"render_*": "png", "render_turntable": "gif"},
)
def render_tumour(mesh: Mesh, brain_mesh: Artifact, config: RenderConfig) -> StageResult:
    """Anatomical views, cut-aways and a turntable of the tumour in its brain (if any).

    ``brain_mesh`` is the surface of the extract-brain-surface stage (empty:
    the tumour is rendered alone).
    """
    artifacts: dict[str, Any] = {}
    values: dict[str, Any] = {"n_views": 0, "renderer": None, "fallback_reason": None}
    if not mesh.is_empty:
        brain = brain_mesh.load()
        result = render_views(mesh, brain=None if brain.is_empty else brain, **config.model_dump())
        for name, rgb in result.images.items():
            artifacts[f"render_{name}"] = Tagged(rgb, {"view": name})
        if result.turntable:
            artifacts["render_turntable"] = turntable_gif(result.turntable)
        values = {
            "n_views": len(result.images),
            "renderer": result.info["renderer"],
            "fallback_reason": result.info["fallback_reason"],
            "seconds": result.info["seconds"],
        }
    return StageResult(artifacts=artifacts, values=values)


SPEC = render_tumour
