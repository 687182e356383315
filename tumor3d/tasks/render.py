"""Adapter of the render-views stage (spec section 7)."""

from __future__ import annotations

from typing import Any

from tumor3d.config import RenderConfig
from tumor3d.storage.objectstore import open_store
from tumor3d.storage.store import ArtifactRef
from tumor3d.tasks.spec import StageOutput, StageSpec, stage_task
from tumor3d.visual.render import render_views, turntable_gif

__all__ = ["SPEC", "render_task"]


@stage_task("render-views")
def render_task(
    mesh: ArtifactRef, brain_mesh: ArtifactRef, config: RenderConfig, store_root: str
) -> StageOutput:
    """Anatomical views, cut-aways and a turntable of the tumour in its brain (if any).

    ``brain_mesh`` is the surface of the extract-brain-surface stage (empty:
    the tumour is rendered alone).
    """
    store = open_store(store_root)
    surface = store.get_mesh(mesh)
    artifacts: dict[str, ArtifactRef] = {}
    values: dict[str, Any] = {"n_views": 0, "renderer": None, "fallback_reason": None}
    if not surface.is_empty:
        brain = store.get_mesh(brain_mesh)
        result = render_views(
            surface, brain=None if brain.is_empty else brain, **config.model_dump()
        )
        for name, rgb in result.images.items():
            artifacts[f"render_{name}"] = store.put_png(rgb, extra={"view": name})
        if result.turntable:
            artifacts["render_turntable"] = store.put_bytes(
                turntable_gif(result.turntable), kind="gif", suffix=".gif"
            )
        values = {
            "n_views": len(result.images),
            "renderer": result.info["renderer"],
            "fallback_reason": result.info["fallback_reason"],
            "seconds": result.info["seconds"],
        }
    return StageOutput(stage="render-views", artifacts=artifacts, values=values)


SPEC = StageSpec(
    name="render-views",
    task=render_task,
    entry=render_views,
    config_model=RenderConfig,
    inputs={"mesh": "mesh", "brain_mesh": "mesh"},
    outputs={"render_*": "png", "render_turntable": "gif"},
)
