"""What every stage adapter shares: its declaration, its output and its task decorator.

* :func:`stage` -- declares one stage around its adapter function: name (spelled
  once), core entry, configuration model, inputs (each with its kind and the
  stage output, the user's source or the given artifact it comes from),
  outputs by kind and the values that become ``metrics.parquet`` columns. The
  adapter receives its inputs loaded by kind and returns a :class:`StageResult`
  of plain values; the decorator stores them by kind
  (:mod:`tumor3d.tasks.kinds`) and returns the :class:`StageSpec`;
* :class:`StageSpec` -- one stage declared: the above plus the Prefect task, a
  cached task whose key comes from :func:`tumor3d.tasks.caching.stage_cache_policy`;
* :class:`StageOutput` -- what a stage task returns (small references, never
  arrays), sealed with a digest of its own content so that a cached result
  edited on disk is detected (:meth:`StageOutput.verify`);
* :class:`InputSource` -- the user's input as the ingest stage sees it.
"""

from __future__ import annotations

import hashlib
import inspect
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

from prefect import task
from pydantic import BaseModel, ConfigDict, Field

from tumor3d.storage.objectstore import open_store
from tumor3d.storage.readers.options import ReadOptions
from tumor3d.storage.store import ArtifactRef, canonical_dumps
from tumor3d.tasks.caching import code_digest, module_closure, stage_cache_policy
from tumor3d.tasks.kinds import Artifact, declared_kind, load, store_product

__all__ = [
    "ALL_VALUES",
    "GIVEN",
    "SOURCE",
    "Input",
    "InputSource",
    "Metric",
    "StageOutput",
    "StageResult",
    "StageSpec",
    "scan_spacing_mm",
    "stage",
]


def scan_spacing_mm(scan: Any) -> tuple[float, float, float]:
    """``(slice step, row, column)`` voxel spacing in mm from a scan artifact's metadata.

    ``scan``: an :class:`ArtifactRef` or an :class:`~tumor3d.tasks.kinds.Artifact` handle.
    """
    dy, dx = scan.metadata["pixel_spacing_mm"]
    return (float(scan.metadata["slice_step_mm"]), float(dy), float(dx))


class StageOutput(BaseModel):
    """What a stage task returns: references and a few scalars, never arrays.

    Parameters
    ----------
    stage : str
        Stage name.
    artifacts : dict of str to ArtifactRef
        The stage's products in the store.
    values : dict
        Small JSON-able results (counts, volumes) for summaries.
    compute_seconds : float
        Wall time of the computation when it actually ran (kept on cache hits).
    key : str
        The cache key the output was computed (and its record stored) under: a
        record found under another key is not this output's (``tumor3d.tasks.records``).
    digest : str
        SHA-256 of the canonical JSON of all other fields ("" until sealed).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    stage: str
    artifacts: dict[str, ArtifactRef] = Field(default_factory=dict)
    values: dict[str, Any] = Field(default_factory=dict)
    compute_seconds: float = 0.0
    key: str = ""
    digest: str = ""

    def content_digest(self) -> str:
        """SHA-256 of every field but ``digest``."""
        body = self.model_dump(mode="json", exclude={"digest"})
        text = canonical_dumps(body).encode()
        return hashlib.sha256(b"tumor3d-stage-output-v1\0" + text).hexdigest()

    def sealed(self) -> StageOutput:
        """A copy carrying its :meth:`content_digest`."""
        return self.model_copy(update={"digest": self.content_digest()})

    def verify(self) -> bool:
        """True if the output is sealed and unchanged since."""
        return bool(self.digest) and self.digest == self.content_digest()


class InputSource(ReadOptions):
    """The user's input, identified by content for caching.

    ``path`` is where to read it; ``digest`` (of the file, or of every file of
    a folder, plus sidecars), ``name`` and the reading options are what the
    cache key sees. The reading options are those of
    :class:`~tumor3d.storage.readers.options.ReadOptions`, declared and checked
    there; here the modality and the patient id are resolved (required). The
    patient id is not in the key (issue 29): the same file under another id is
    the same scan, so every stage's key depends on the content alone; no stage
    output carries the id (the scan artifact does not store it), and the flow
    names the patient when it publishes.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    path: str
    name: str
    digest: str
    #: Resolved: the sequence read (``"t2"`` when none was given) and the id published as.
    modality: str
    patient_id: str
    #: The patient id was derived from the file name (no ``--patient-id``): publishing
    #: then never replaces another input's results (``tumor3d.storage.publish.check_same_input``).
    id_derived: bool = False
    #: Nothing named the modality (no option, no manifest value, no sidecar): ``modality``
    #: is the default, which the run's notes say.
    modality_default: bool = False

    #: Where the input lives, which patient it is published as, and how that id or the
    #: modality was chosen, do not change what it is.
    __cache_exclude__: ClassVar[frozenset[str]] = frozenset(
        {"path", "patient_id", "id_derived", "modality_default"}
    )


#: Where an input comes from, besides another stage's output (``"<stage>.<artifact>"``).
SOURCE = "source"  # the user's input (:class:`InputSource`)
GIVEN = "given:"  # an artifact the flow provides: ``given:<name>`` (a given mask, a reference)


@dataclass(frozen=True)
class Input:
    """One declared input of a stage.

    Parameters
    ----------
    kind : str
        Artifact kind (:data:`tumor3d.tasks.kinds.KINDS`), or ``"source"``.
    source : str
        ``"<stage>.<artifact>"`` (that stage's product, which must be of this
        kind), ``"source"`` (the user's input) or ``"given:<name>"`` (an
        artifact the flow provides, e.g. ``given:brain_mask``).
    load : bool
        True: the adapter receives the content (:mod:`tumor3d.tasks.kinds`);
        False: an :class:`~tumor3d.tasks.kinds.Artifact` handle (metadata, and
        the content on ``load()``).
    optional : bool
        May be None (a given artifact the user may not give).
    """

    kind: str
    source: str
    load: bool = True
    optional: bool = False

    @property
    def producer(self) -> tuple[str, str] | None:
        """``(stage, artifact)`` for another stage's product, else None."""
        if self.source == SOURCE or self.source.startswith(GIVEN):
            return None
        stage_name, _, artifact = self.source.partition(".")
        return stage_name, artifact


@dataclass(frozen=True)
class Metric:
    """A stage value published as a ``metrics.parquet`` column.

    ``value``: the key in :attr:`StageOutput.values`; ``description``: what
    the column holds, with its unit (the column's name says the unit too).
    """

    value: str
    description: str


#: ``metrics=ALL_VALUES``: every value of the stage is a column under its own name.
ALL_VALUES = "*"


@dataclass(frozen=True)
class StageResult:
    """What an adapter returns: products by name (stored by their declared kind) and values."""

    artifacts: Mapping[str, Any]
    values: Mapping[str, Any]


@dataclass(frozen=True)
class StageSpec:
    """One pipeline stage, declared.

    Parameters
    ----------
    name : str
        Stage name (``extract-surface``); also the Prefect task name.
    task : prefect.Task
        The adapter as a cached Prefect task (made by :func:`stage`).
    entry : callable
        The core function the adapter calls (for documentation and tests).
    config_model : type of pydantic.BaseModel or None
        The stage's configuration (``PipelineConfig`` field of that type), if any.
    inputs : mapping of str to Input
        Task parameter -> :class:`Input` (its kind and where it comes from).
    outputs : mapping of str to str
        Artifact name (or ``fnmatch`` pattern) in :attr:`StageOutput.artifacts` -> kind.
    metrics : mapping of str to Metric, or ``"*"``
        ``metrics.parquet`` column -> the value it holds (:data:`ALL_VALUES`:
        every value, under its own name).
    """

    name: str
    task: Any
    entry: Callable[..., Any]
    config_model: type[BaseModel] | None
    inputs: Mapping[str, Input]
    outputs: Mapping[str, str]
    metrics: Mapping[str, Metric] | str = field(default_factory=dict)

    def __post_init__(self) -> None:
        # a bare kind: the user's source (``"source"``) or not wired
        inputs = {
            k: v if isinstance(v, Input) else Input(v, SOURCE if v == SOURCE else "")
            for k, v in self.inputs.items()
        }
        object.__setattr__(self, "inputs", inputs)

    @property
    def adapter_module(self) -> str:
        """Dotted name of the adapter module (the root of the code closure)."""
        return self.task.fn.__module__

    @property
    def code_modules(self) -> tuple[str, ...]:
        """Every project module in the stage's code digest."""
        return module_closure((self.adapter_module,))

    @property
    def code_digest(self) -> str:
        """The stage's code digest (see :func:`tumor3d.tasks.caching.code_digest`)."""
        return code_digest((self.adapter_module,))

    def metric_columns(self, values: Mapping[str, Any]) -> dict[str, Any]:
        """The stage's ``metrics.parquet`` columns from its output's ``values``."""
        if self.metrics == ALL_VALUES:
            return dict(values)
        assert not isinstance(self.metrics, str)
        return {col: values[m.value] for col, m in self.metrics.items()}


def stage(
    name: str,
    *,
    entry: Callable[..., Any],
    inputs: Mapping[str, Input],
    outputs: Mapping[str, str],
    config: type[BaseModel] | None = None,
    metrics: Mapping[str, Metric] | str | None = None,
) -> Callable[[Callable[..., StageResult]], StageSpec]:
    """Declare a stage around its adapter function; returns the :class:`StageSpec`.

    The adapter ``fn(**inputs, config=...)`` receives every input of
    ``inputs`` loaded by its kind (:func:`tumor3d.tasks.kinds.load`; an
    :class:`~tumor3d.tasks.kinds.Artifact` handle where ``load=False``; None
    for an absent optional one) and ``config`` when the stage has one; it
    returns a :class:`StageResult` whose products are stored under the kinds
    ``outputs`` declares. The Prefect task (:func:`_cached_task`) takes the
    references instead, plus ``store_root``: its parameters, and so its cache
    key, are the inputs' references by digest, the configuration and the
    stage's code, whose closure is rooted at ``fn``'s module.
    """

    def decorate(fn: Callable[..., StageResult]) -> StageSpec:
        def adapter(**kwargs: Any) -> StageOutput:
            store = open_store(kwargs.pop("store_root"))
            args: dict[str, Any] = {}
            for key, value in kwargs.items():
                spec = inputs.get(key)
                if spec is None or value is None or spec.kind == SOURCE:
                    args[key] = value  # the configuration, an absent input, the user's source
                elif spec.load:
                    args[key] = load(store, value)
                else:
                    args[key] = Artifact(value, store)
            result = fn(**args)
            stored = {}
            for product, value in result.artifacts.items():
                kind = declared_kind(outputs, product)
                if kind is None:
                    raise TypeError(f"stage {name}: product {product!r} is not declared")
                stored[product] = store_product(store, kind, value)
            return StageOutput(stage=name, artifacts=stored, values=dict(result.values))

        params = [
            inspect.Parameter(key, inspect.Parameter.KEYWORD_ONLY)
            for key, i in inputs.items()
            if not i.optional
        ]
        if config is not None:
            params.append(inspect.Parameter("config", inspect.Parameter.KEYWORD_ONLY))
        params.append(inspect.Parameter("store_root", inspect.Parameter.KEYWORD_ONLY))
        params += [
            inspect.Parameter(key, inspect.Parameter.KEYWORD_ONLY, default=None)
            for key, i in inputs.items()
            if i.optional
        ]
        adapter.__signature__ = inspect.Signature(params)  # type: ignore[attr-defined]
        adapter.__name__ = fn.__name__
        adapter.__qualname__ = fn.__qualname__
        adapter.__doc__ = fn.__doc__
        adapter.__module__ = fn.__module__  # the root of the stage's code closure
        return StageSpec(
            name=name,
            task=_cached_task(name, adapter),
            entry=entry,
            config_model=config,
            inputs=dict(inputs),
            outputs=dict(outputs),
            metrics={} if metrics is None else metrics,
        )

    return decorate


def _cached_task(name: str, fn: Callable[..., StageOutput]) -> Any:
    """The cached Prefect task of stage ``name`` around its adapter ``fn`` (made by :func:`stage`).

    The key is :func:`tumor3d.tasks.caching.stage_cache_policy` with the adapter's
    module as the closure root; the result (a sealed :class:`StageOutput`
    carrying that key) is persisted as plain JSON by
    :class:`tumor3d.tasks.records.StageOutputSerializer`, never pickled. Result storage
    is set per run by the runner (:mod:`tumor3d.tasks.runner`) to the artifact store's
    folder, whose records are screened before Prefect decodes them.
    """
    from tumor3d.tasks.records import StageOutputSerializer

    policy = stage_cache_policy(name, (fn.__module__,))
    signature = inspect.signature(fn)

    def timed(*args: Any, **kwargs: Any) -> StageOutput:
        t0 = time.perf_counter()
        out = fn(*args, **kwargs)
        bound = signature.bind(*args, **kwargs)
        bound.apply_defaults()  # as Prefect's task parameters
        key = policy.compute_key(None, dict(bound.arguments), {})
        update = {"compute_seconds": time.perf_counter() - t0, "key": key or ""}
        return out.model_copy(update=update).sealed()

    timed.__name__ = fn.__name__
    timed.__qualname__ = fn.__qualname__
    timed.__doc__ = fn.__doc__
    timed.__module__ = fn.__module__
    timed.__wrapped__ = fn  # type: ignore[attr-defined]
    return task(
        name=name,
        task_run_name=name,
        cache_policy=policy,
        persist_result=True,
        result_serializer=StageOutputSerializer(),
        # Prefect's in-memory result cache is an LRUCache shared by every
        # thread of a flow and not thread-safe: with patients running in
        # parallel lanes it made random cached stages look like misses.
        # Results are small; read them from the store instead.
        cache_result_in_memory=False,
        retries=0,
    )(timed)
