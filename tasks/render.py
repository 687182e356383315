"""Adapter of the render-views stage (spec section 7)."""

from __future__ import annotations

from storage.store import ArtifactRef, ArtifactStore
from tasks.spec import StageOutput, StageSpec, stage_task
from tumor3d.config import RenderConfig
from tumor3d.render import render_views

__all__ = ["SPEC", "render_task"]


@stage_task("render-views")
def render_task(mesh: ArtifactRef, config: RenderConfig, store_root: str) -> StageOutput:
    """Shaded offscreen renders of the surface from several azimuths (none without tumour)."""
    store = ArtifactStore(store_root)
    surface = store.get_mesh(mesh)
    artifacts: dict[str, ArtifactRef] = {}
    if not surface.is_empty:
        images = render_views(surface, **config.model_dump())
        for azimuth, rgb in zip(config.azimuths_deg, images, strict=True):
            name = f"render_az{int(round(azimuth)) % 360:03d}"
            artifacts[name] = store.put_png(rgb, extra={"azimuth_deg": float(azimuth)})
    return StageOutput(
        stage="render-views", artifacts=artifacts, values={"n_views": len(artifacts)}
    )


SPEC = StageSpec(
    name="render-views",
    task=render_task,
    entry=render_views,
    config_model=RenderConfig,
    inputs={"mesh": "mesh"},
    outputs={"render_az*": "png"},
)
