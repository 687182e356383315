"""The registry of pipeline stages, in pipeline order.

Each stage is declared by the :class:`~tumor3d.tasks.spec.StageSpec` of its adapter
module (``tumor3d/tasks/ingest.py`` ... ``tumor3d/tasks/measure.py``); this module only
collects them. No adapter imports this module, so editing it changes no
stage's code digest.
"""

from __future__ import annotations

from tumor3d.tasks import (
    brain_surface,
    detect,
    ingest,
    interpolate,
    measure,
    preprocess,
    render,
    segment,
    simplify,
)
from tumor3d.tasks import surface as surface_adapter
from tumor3d.tasks.spec import InputSource, StageOutput, StageSpec

__all__ = [
    "STAGES",
    "brain_surface_task",
    "InputSource",
    "StageOutput",
    "StageSpec",
    "detect_task",
    "ingest_task",
    "interpolate_task",
    "measure_task",
    "preprocess_task",
    "render_task",
    "segment_task",
    "simplify_task",
    "stage_modules",
    "surface_task",
]

#: Stage name -> its declaration, in the order the pipeline runs them.
STAGES: dict[str, StageSpec] = {
    spec.name: spec
    for spec in (
        ingest.SPEC,
        preprocess.SPEC,
        detect.SPEC,
        segment.SPEC,
        interpolate.SPEC,
        surface_adapter.SPEC,
        simplify.SPEC,
        brain_surface.SPEC,
        render.SPEC,
        measure.SPEC,
    )
}

ingest_task = ingest.ingest_task
preprocess_task = preprocess.preprocess_task
detect_task = detect.detect_task
segment_task = segment.segment_task
interpolate_task = interpolate.interpolate_task
surface_task = surface_adapter.surface_task
simplify_task = simplify.simplify_task
brain_surface_task = brain_surface.brain_surface_task
render_task = render.render_task
measure_task = measure.measure_task


def stage_modules(name: str) -> tuple[str, ...]:
    """Every project module whose source enters stage ``name``'s code digest."""
    return STAGES[name].code_modules
