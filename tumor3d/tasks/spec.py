"""What every stage adapter shares: its declaration, its output and its task decorator.

* :class:`StageSpec` -- one stage declared: name, core entry function,
  configuration model, input and output artifact kinds, the Prefect task;
* :class:`StageOutput` -- what a stage task returns (small references, never
  arrays), sealed with a digest of its own content so that a cached result
  edited on disk is detected (:meth:`StageOutput.verify`);
* :class:`InputSource` -- the user's input as the ingest stage sees it;
* :func:`stage_task` -- makes an adapter function a cached Prefect task whose
  key comes from :func:`tumor3d.tasks.caching.stage_cache_policy`.
"""

from __future__ import annotations

import hashlib
import inspect
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from prefect import task
from pydantic import BaseModel, ConfigDict, Field

from tumor3d.constants import MAX_VOXELS_DEFAULT
from tumor3d.storage.store import ArtifactRef, canonical_dumps
from tumor3d.tasks.caching import code_digest, module_closure, stage_cache_policy

__all__ = ["InputSource", "StageOutput", "StageSpec", "scan_spacing_mm", "stage_task"]


def scan_spacing_mm(scan: ArtifactRef) -> tuple[float, float, float]:
    """``(slice step, row, column)`` voxel spacing in mm from a scan artifact's metadata."""
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


class InputSource(BaseModel):
    """The user's input, identified by content for caching.

    ``path`` is where to read it; ``digest`` (of the file, or of every file of
    a folder, plus sidecars), ``name`` and the reading options are what the
    cache key sees. The patient id is not (issue 29): the same file under
    another id is the same scan, so every stage's key depends on the content
    alone; no stage output carries the id (the scan artifact does not store
    it), and the flow names the patient when it publishes.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    path: str
    name: str
    digest: str
    modality: str
    patient_id: str
    series_uid: str | None = None
    slice_thickness_mm: float | None = None
    slice_gap_mm: float | None = None
    #: Skip DICOM files that cannot be read (listed in the scan) instead of stopping.
    skip_unreadable: bool = False
    #: Refuse an input whose header declares more voxels (checked before reading).
    max_voxels: int = MAX_VOXELS_DEFAULT
    #: The patient id was derived from the file name (no ``--patient-id``): publishing
    #: then never replaces another input's results (``tumor3d.storage.publish.check_same_input``).
    id_derived: bool = False

    #: Where the input lives, which patient it is published as, and how that id was
    #: chosen, do not change what it is.
    __cache_exclude__: ClassVar[frozenset[str]] = frozenset({"path", "patient_id", "id_derived"})


@dataclass(frozen=True)
class StageSpec:
    """One pipeline stage, declared.

    Parameters
    ----------
    name : str
        Stage name (``extract-surface``); also the Prefect task name.
    task : prefect.Task
        The adapter as a cached Prefect task (made by :func:`stage_task`).
    entry : callable
        The core function the adapter calls (for documentation and tests).
    config_model : type of pydantic.BaseModel or None
        The stage's configuration (``PipelineConfig`` field of that type), if any.
    inputs : mapping of str to str
        Task parameter -> artifact kind it expects (``scan``, ``mask``, ...),
        or ``"source"`` for the user's input.
    outputs : mapping of str to str
        Artifact name in :attr:`StageOutput.artifacts` -> kind.
    """

    name: str
    task: Any
    entry: Callable[..., Any]
    config_model: type[BaseModel] | None
    inputs: Mapping[str, str]
    outputs: Mapping[str, str]

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


def stage_task(name: str) -> Callable[[Callable[..., StageOutput]], Any]:
    """Decorate an adapter function as the cached Prefect task of stage ``name``.

    The key is :func:`tumor3d.tasks.caching.stage_cache_policy` with the adapter's
    module as the closure root; the result (a sealed :class:`StageOutput`
    carrying that key) is persisted as plain JSON by
    :class:`tumor3d.tasks.records.StageOutputSerializer`, never pickled. Result storage
    is set per run by the runner (:mod:`tumor3d.tasks.runner`) to the artifact store's
    folder, whose records are screened before Prefect decodes them.
    """

    def decorate(fn: Callable[..., StageOutput]) -> Any:
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

    return decorate
