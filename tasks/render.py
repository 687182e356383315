"""Adapter of the render-views stage (spec section 7)."""

from __future__ import annotations

from typing import Any

from storage.objectstore import open_store
from storage.store import ArtifactRef
from tasks.spec import StageOutput, StageSpec, stage_task
from tumor3d.config import RenderConfig
from tumor3d.render import brain_surface, render_views, turntable_gif

__all__ = ["SPEC", "render_task"]

#: Grid spacing of the translucent brain surface (a context surface, not a measurement).
BRAIN_SURFACE_SPACING_MM = 2.0


@stage_task("render-views")
def render_task(
    mesh: ArtifactRef, brain_mask: ArtifactRef, config: RenderConfig, store_root: str
) -> StageOutput:
    """Anatomical views, cut-aways and a turntable of the tumour in its brain (if any)."""
    store = open_store(store_root)
    surface = store.get_mesh(mesh)
    artifacts: dict[str, ArtifactRef] = {}
    values: dict[str, Any] = {"n_views": 0, "renderer": None, "fallback_reason": None}
    if not surface.is_empty:
        brain_zyx, affine = store.get_volume(brain_mask)
        brain = brain_surface(brain_zyx, affine, spacing_mm=BRAIN_SURFACE_SPACING_MM)
        result = render_views(surface, brain=brain, **config.model_dump())
        artifacts["brain_mesh"] = store.put_mesh(brain)
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
        }
    return StageOutput(stage="render-views", artifacts=artifacts, values=values)


SPEC = StageSpec(
    name="render-views",
    task=render_task,
    entry=render_views,
    config_model=RenderConfig,
    inputs={"mesh": "mesh", "brain_mask": "mask"},
    outputs={"render_*": "png", "render_turntable": "gif", "brain_mesh": "mesh"},
)
