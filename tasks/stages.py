"""The registry of pipeline stages, in pipeline order, and the wiring read from it.

Each stage is declared by the :class:`~tumor3d.tasks.spec.StageSpec` of its adapter
module (``tasks/ingest.py`` ... ``tasks/measure.py``); this module
collects them (:data:`STAGES`), feeds a stage its inputs from the declarations
(:func:`stage_inputs`: each input names the stage output, the user's source or
the given artifact it comes from), finds the stages another stage needs
(:func:`upstream`), checks that wiring (:func:`wiring_errors`; :func:`check_wiring`
raises, and runs on :data:`STAGES` when this module is imported) and gathers the
declared ``metrics.parquet`` columns (:func:`metric_columns`).
No adapter imports this module, so editing it changes no stage's code digest.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterable, Mapping
from typing import Any

from pydantic import BaseModel

from tumor3d.config import PipelineConfig
from tumor3d.learned.bundle import pack_models
from tumor3d.storage.brain_mask import GivenBrainMask
from tumor3d.storage.given_segmentation import GivenSegmentation
from tumor3d.storage.refs import ArtifactRef
from tumor3d.storage.store import ArtifactStore
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
from tumor3d.tasks.spec import GIVEN, SOURCE, Input, InputSource, StageOutput, StageSpec

__all__ = [
    "STAGES",
    "InputSource",
    "StageOutput",
    "StageSpec",
    "check_wiring",
    "code_digests",
    "config_field",
    "metric_columns",
    "product",
    "stage_inputs",
    "stage_modules",
    "store_given",
    "upstream",
    "wiring_errors",
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


def code_digests() -> dict[str, str]:
    """Stage name -> the digest of its code, as its cache key and ``provenance.json`` hold it."""
    return {name: spec.code_digest for name, spec in STAGES.items()}


def stage_modules(name: str) -> tuple[str, ...]:
    """Every project module whose source enters stage ``name``'s code digest."""
    return STAGES[name].code_modules


def config_field(spec: StageSpec) -> str | None:
    """The :class:`~tumor3d.config.PipelineConfig` field holding ``spec``'s configuration."""
    if spec.config_model is None:
        return None
    model = spec.config_model
    fields = [k for k, f in PipelineConfig.model_fields.items() if f.annotation is model]
    if len(fields) != 1:
        raise LookupError(f"stage {spec.name}: no single PipelineConfig field of its model")
    return fields[0]


def store_given(
    store: ArtifactStore,
    *,
    brain_mask: GivenBrainMask | None = None,
    segmentation: GivenSegmentation | None = None,
    models: Mapping[str, bytes] | None = None,
    models_folder: str | None = None,
) -> dict[str, ArtifactRef | None]:
    """The given artifacts of a run, stored: ``given:`` brain_mask, segmentation, models.

    Content-addressed (the same mask, the same reference); a segmentation's
    file name rides along in its metadata (``given_file``: the stage's
    ``measured`` names it). ``models``: a user's trained model files
    (``segment.learned_models``, :func:`tumor3d.storage.given_models.read_given_models`),
    packed into one object (:func:`tumor3d.learned.bundle.pack_models`) whose digest
    is their content's and their folder's (``models_folder``, which provenance names):
    their names, SHA-256 and folder ride in its metadata. The configuration's path
    keys nothing itself (``SegmentConfig.__cache_exclude__``): a run that uses no
    model is not recomputed for a folder named.
    """
    return {
        "models": None
        if models is None
        else store.put_bytes(
            pack_models(models),
            kind="models",
            suffix=".npz",
            metadata={
                "files": {n: hashlib.sha256(b).hexdigest() for n, b in sorted(models.items())},
                "folder": models_folder,
            },
        ),
        "brain_mask": None
        if brain_mask is None
        else store.put_volume(brain_mask.mask, brain_mask.affine, kind="mask"),
        "segmentation": None
        if segmentation is None
        else store.put_volume(
            segmentation.mask,
            segmentation.affine,
            kind="mask",
            extra={"given_file": segmentation.name},
        ),
    }


def stage_inputs(
    spec: StageSpec,
    outputs: Mapping[str, StageOutput],
    *,
    source: InputSource | None = None,
    cfg: BaseModel | None = None,
    given: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """The task inputs of ``spec`` (less ``store_root``), from its declarations.

    Each declared input is taken from the output of the stage it names (in
    ``outputs``, stage name -> output), the user's ``source``, or ``given``
    (``given:<name>``: an artifact the flow stored, None when absent and the
    input optional); ``config`` is the stage's field of ``cfg``.

    Raises
    ------
    KeyError
        An input whose stage has not run, or a required given artifact absent.
    """
    given = given or {}
    kwargs: dict[str, Any] = {}
    for name, declared in spec.inputs.items():
        if declared.source == SOURCE:
            kwargs[name] = source
        elif declared.producer is not None:
            kwargs[name] = product(outputs, declared)
        else:
            value = given.get(declared.source.removeprefix(GIVEN))
            if value is None and not declared.optional:
                raise KeyError(f"stage {spec.name}: input {name} ({declared.source}) not given")
            kwargs[name] = value
    field = config_field(spec)
    if field is not None:
        kwargs["config"] = getattr(cfg, field)
    return kwargs


def product(outputs: Mapping[str, StageOutput], declared: Input) -> ArtifactRef:
    """The stage product a declared input takes, from ``outputs`` (stage name -> output).

    Raises
    ------
    KeyError
        Its stage has not run, or did not make that product.
    ValueError
        The input comes from the source or is given, not from a stage.
    """
    if declared.producer is None:
        raise ValueError(f"input from {declared.source!r} is no stage's product")
    stage_name, artifact = declared.producer
    return outputs[stage_name].artifacts[artifact]


def upstream(*specs: StageSpec) -> list[StageSpec]:
    """The stages of :data:`STAGES` whose products ``specs`` need, transitively, in order.

    What a run of ``specs`` alone (training's stages, say) must run first: the
    stages their inputs name, the stages those take theirs from, and so on.

    Raises
    ------
    KeyError
        An input names a stage that is not in :data:`STAGES`.
    """

    def producers(spec: StageSpec) -> list[str]:
        return [i.producer[0] for i in spec.inputs.values() if i.producer is not None]

    needed: set[str] = set()
    todo = [name for spec in specs for name in producers(spec)]
    while todo:
        name = todo.pop()
        if name in needed:
            continue
        if name not in STAGES:
            raise KeyError(f"an input comes from {name!r}, which is not a stage of STAGES")
        needed.add(name)
        todo.extend(producers(STAGES[name]))
    return [spec for name, spec in STAGES.items() if name in needed]


def wiring_errors(specs: Iterable[StageSpec]) -> list[str]:
    """What is wrong with running ``specs`` in this order: [] when every input is produced.

    Every input taken from a stage must name an earlier stage and one of its
    declared outputs, of the same kind; every other input is the source (of
    kind ``source``) or a given artifact.
    """
    errors: list[str] = []
    produced: dict[str, Mapping[str, str]] = {}
    for spec in specs:
        for name, declared in spec.inputs.items():
            where = f"{spec.name}.{name}"
            producer = declared.producer
            if producer is None:
                if (declared.source == SOURCE) != (declared.kind == SOURCE):
                    errors.append(f"{where}: kind {declared.kind!r} from {declared.source!r}")
                elif declared.source != SOURCE and not declared.source.startswith(GIVEN):
                    errors.append(f"{where}: comes from nowhere ({declared.source!r})")
                continue
            stage_name, artifact = producer
            if stage_name not in produced:
                errors.append(f"{where}: {stage_name} has not run before {spec.name}")
            elif produced[stage_name].get(artifact) != declared.kind:
                got = produced[stage_name].get(artifact)
                errors.append(f"{where}: {declared.source} is {got!r}, not {declared.kind!r}")
        produced[spec.name] = spec.outputs
    return errors


def check_wiring(specs: Iterable[StageSpec]) -> None:
    """Raise unless running ``specs`` in this order feeds every input (:func:`wiring_errors`).

    Raises
    ------
    TypeError
        Naming every input that is wrong (a declaration to fix, not a user's error).
    """
    errors = wiring_errors(specs)
    if errors:
        raise TypeError("stage declarations do not wire up: " + "; ".join(errors))


def metric_columns(outputs: Mapping[str, StageOutput]) -> dict[str, Any]:
    """The ``metrics.parquet`` columns the stages declare, from their outputs, in stage order."""
    row: dict[str, Any] = {}
    for name, spec in STAGES.items():
        if name in outputs:
            row.update(spec.metric_columns(outputs[name].values))
    return row


check_wiring(STAGES.values())  # once, at import: a declaration that breaks the pipeline fails here
