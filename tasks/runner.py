"""Runners: how a flow executes one stage.

A runner's ``run(spec, **inputs)`` executes the stage declared by ``spec``
and returns its :class:`~tumor3d.tasks.spec.StageOutput`; :attr:`runs` records how
each went (:class:`StageRun`).

* :class:`PrefectRunner` *submits* the stage's cached Prefect task to the
  current flow's task runner (``task.submit``, a Prefect future), so the
  flow's task runner decides where it executes (threads by default; a Dask
  task runner can be plugged into the flow without changing any stage). It
  keeps Prefect's results in the artifact store's ``prefect-results`` folder
  and repairs cache hits that cannot be trusted: a cached result whose
  artifacts are gone from the store or fail their digest check
  (:meth:`~tumor3d.storage.store.ArtifactStore.verify`, which quarantines a corrupted
  object), or whose own digest does not match its content (edited on disk),
  is recomputed (``refresh_cache``) and the repair recorded.
* :class:`DirectRunner` calls the adapter function in-process without
  Prefect (no caching): benchmarks' peer and in-process evaluation.
"""

from __future__ import annotations

import hashlib
import logging
import threading
import time
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from tumor3d.errors import exception_line
from tumor3d.storage.store import ArtifactStore
from tumor3d.tasks.progress import ProgressEvent, report
from tumor3d.tasks.records import UntrustedRecord
from tumor3d.tasks.spec import StageOutput, StageSpec

__all__ = ["DirectRunner", "PrefectRunner", "StageRun", "result_storage_for", "stage_key"]

_log = logging.getLogger("tumor3d.runner")


class StageRun(BaseModel):
    """How one stage went in this flow run.

    Parameters
    ----------
    stage : str
    cached : bool
        The result came from the cache (and passed its checks).
    wall_seconds : float
        Time this run spent on the stage (submission to result).
    compute_seconds : float
        Time of the computation when it last actually ran.
    artifacts : dict of str to str
        Artifact name -> content digest.
    repaired : str or None
        Why a cache hit was rejected and the stage recomputed, if it was.
    """

    model_config = ConfigDict(frozen=True)

    stage: str
    cached: bool
    wall_seconds: float
    compute_seconds: float
    artifacts: dict[str, str] = Field(default_factory=dict, description="name -> digest")
    repaired: str | None = None


def result_storage_for(store: ArtifactStore | str | Path) -> Any:
    """Prefect result storage inside an artifact store: ``<store>/prefect-results``.

    A :class:`~tumor3d.tasks.records.ScreenedResultFolder` for a local store, a
    :class:`~tumor3d.tasks.records.ScreenedRemoteFolder` on ``<url>/prefect-results``
    for an object store (:class:`tumor3d.storage.objectstore.ObjectStore`): every
    record is screened (plain JSON, this project's serializer, the key it is
    stored under) before Prefect decodes it. Prefect requires a task's result
    storage block to be saved on the server: each is saved once per process
    and server as ``tumor3d-results-<hash of the path or URL>`` (the local
    one when first used; every Dask worker reads the same cache).
    """
    url = getattr(store, "url", None)
    if url is not None:
        return _remote_result_storage(url, store.storage_options)  # type: ignore[union-attr]
    root = store.root if isinstance(store, ArtifactStore) else store
    path = Path(root).resolve() / "prefect-results"
    path.mkdir(parents=True, exist_ok=True)
    return _local_result_storage(path)


_REMOTE_STORAGE: dict[str, Any] = {}


def _server() -> str:
    from prefect.settings import PREFECT_API_URL

    return str(PREFECT_API_URL.value())


def _local_result_storage(path: Path) -> Any:
    from tumor3d.tasks.records import ScreenedResultFolder

    key = f"{_server()}|{path}"
    with _TASKS_LOCK:
        block = _REMOTE_STORAGE.get(key)
        if block is None:
            block = ScreenedResultFolder(basepath=str(path))  # saved when first used
            _REMOTE_STORAGE[key] = block
    return block


def _remote_result_storage(url: str, options: dict[str, Any]) -> Any:
    from tumor3d.tasks.records import ScreenedRemoteFolder

    key = f"{_server()}|{url}"  # saved on this server
    with _TASKS_LOCK:
        block = _REMOTE_STORAGE.get(key)
        if block is None:
            block = ScreenedRemoteFolder(basepath=f"{url}/prefect-results", settings=options)
            name = "tumor3d-results-" + hashlib.sha256(url.encode()).hexdigest()[:16]
            block.save(name, overwrite=True)
            _REMOTE_STORAGE[key] = block
    return block


class _Recorder:
    """Bookkeeping shared by the runners."""

    def __init__(self, patient_id: str, total: int, runs: list[StageRun] | None = None) -> None:
        self.patient_id = patient_id
        self.total = total
        self.runs: list[StageRun] = runs if runs is not None else []
        self.outputs: dict[str, StageOutput] = {}

    def started(self, name: str) -> None:
        report(ProgressEvent(self.patient_id, name, "started", len(self.runs), self.total))

    def finished(
        self, out: StageOutput, *, cached: bool, wall: float, repaired: str | None = None
    ) -> StageOutput:
        self.runs.append(
            StageRun(
                stage=out.stage,
                cached=cached,
                wall_seconds=wall,
                compute_seconds=out.compute_seconds,
                artifacts={k: r.digest for k, r in out.artifacts.items()},
                repaired=repaired,
            )
        )
        self.outputs[out.stage] = out
        status = "cached" if cached else "done"
        report(ProgressEvent(self.patient_id, out.stage, status, len(self.runs), self.total, wall))
        return out


_TASKS: dict[tuple[str, str, bool, str], Any] = {}
_TASKS_LOCK = threading.Lock()


def _task_for(spec: StageSpec, result_storage: Any, refresh: bool, patient_id: str) -> Any:
    """The stage's task with this store's result storage, its runs named after the patient.

    ``result_storage`` is a folder, or a Prefect file-system block for an
    object store. Made once per process and key (``with_options`` builds a
    new task).
    """
    where = str(getattr(result_storage, "basepath", result_storage))
    key = (spec.name, where, refresh, patient_id)
    with _TASKS_LOCK:
        if getattr(result_storage, "_block_document_id", None) is None:
            # Prefect requires a saved block: one per folder, named after its path
            digest = hashlib.sha256(where.encode()).hexdigest()[:16]
            result_storage.save(f"tumor3d-results-{digest}", overwrite=True)
        task = _TASKS.get(key)
        if task is None or task.fn is not spec.task.fn:
            task = spec.task.with_options(
                result_storage=result_storage,
                refresh_cache=refresh,
                task_run_name=f"{spec.name}-{patient_id}" if patient_id else spec.name,
            )
            _TASKS[key] = task
    return task


class PrefectRunner(_Recorder):
    """Submit each stage's cached Prefect task from inside a flow.

    Parameters
    ----------
    store : ArtifactStore
        Where artifacts and Prefect's results live.
    patient_id : str
        For progress events.
    total : int
        Number of stages (for progress events).
    runs : list of StageRun, optional
        Filled as stages complete (default: a new list, :attr:`runs`).
    """

    def __init__(
        self,
        store: ArtifactStore,
        patient_id: str,
        total: int,
        runs: list[StageRun] | None = None,
    ) -> None:
        super().__init__(patient_id, total, runs)
        self.store = store
        self.result_storage = result_storage_for(store)

    def _submit(self, spec: StageSpec, *, refresh: bool, **inputs: Any) -> Any:
        from prefect.context import TagsContext

        task = _task_for(spec, self.result_storage, refresh, self.patient_id)
        # The stage's task run carries no tags: the flow run keeps the ``config:<digest>``
        # and ``cohort`` tags (``run_patient``, ``run_cohort``), which task runs would
        # inherit, and Prefect asks the server for tag concurrency slots (one round
        # trip through a single service thread) for every task run that has a tag:
        # 0.27 s a stage on 2 busy cores, the largest item of a cohort's orchestration.
        with TagsContext(current_tags=set()):
            future = task.submit(**inputs)
        future.wait()
        wrapped = getattr(future, "wrapped_future", None)
        if wrapped is not None and getattr(wrapped, "status", None) == "error":
            # Dask itself gave up (KilledWorker: every worker that ran it died): the task
            # run never finished, so its Prefect state says Pending/Running; name the cause
            raise wrapped.exception()
        return future.state

    def _record_check(self, key: str | None) -> str | None:
        """Before submitting: is a record stored under ``key``, would it be trusted.

        None if there is none; else why the screen would refuse it ("" if it
        would trust it).
        """
        from tumor3d.tasks.records import why_refused

        try:
            record = self.result_storage.read_raw(key) if key else None
        except UntrustedRecord as exc:
            return str(exc)  # present, but not a file to read (a symlink)
        except Exception as exc:  # diagnostics only: never fail a stage for it
            # a local record that is there but cannot be read (too many open files, a
            # permission) is named, not taken for an absent one
            where = getattr(self.result_storage, "_record_path", None)
            try:
                present = where is not None and where(key).exists()
            except Exception:
                present = False
            return f"unreadable ({exception_line(exc)})" if present else None
        return None if record is None else (why_refused(record, key) or "")

    def run(self, spec: StageSpec, **inputs: Any) -> StageOutput:
        """Run one stage (cached), repairing an untrustworthy cache hit."""
        self.started(spec.name)
        t0 = time.perf_counter()
        key = stage_key(spec, inputs)
        check = self._record_check(key)
        state = self._submit(spec, refresh=False, **inputs)
        cached = state.name == "Cached"
        repaired = missed = None
        if not cached and check is not None:
            # Issue 6's intermittent miss: Prefect's ResultStore.exists() swallows any
            # error reading a record (and the screen's refusals) and reports a miss;
            # name it instead of nothing.
            missed = (
                f"cache record present but refused: {check}"
                if check
                else "cache record present and trusted; Prefect missed it"
            )
            _log.warning("%s: recomputed although its cache record existed: %s", spec.name, missed)
        try:
            out: StageOutput = state.result()
        except Exception as exc:
            if not cached:
                raise
            out, repaired = None, f"cached result unreadable ({type(exc).__name__})"  # type: ignore[assignment]
        if cached and repaired is None:
            repaired = self._distrust(out, stage=spec.name)
        if repaired is not None:
            _log.warning("%s: %s; recomputing", spec.name, repaired)
            out = self._submit(spec, refresh=True, **inputs).result()
            cached = False
        wall = time.perf_counter() - t0
        return self.finished(out, cached=cached, wall=wall, repaired=repaired or missed)

    def _distrust(self, out: Any, stage: str | None = None) -> str | None:
        """Why a cached output cannot be used, or None if it can.

        ``stage``, when given, is the stage it was looked up for: another
        stage's output is not used. (A record stored under another key than
        the one Prefect read it under is refused before it is decoded:
        :func:`tumor3d.tasks.records.screen_record`.)
        """
        if not isinstance(out, StageOutput):
            return f"cached result is a {type(out).__name__}, not a StageOutput"
        if not out.verify():
            return "cached result failed its digest check (edited or corrupted)"
        if stage is not None and out.stage != stage:
            return f"cached result is the {out.stage} stage's, not {stage}'s"

        # verify(): present AND content matching its digest; a corrupted object is
        # quarantined by the store, so recomputing the stage writes it afresh
        bad = [k for k, r in out.artifacts.items() if not self.store.verify(r)]
        if bad:
            return (
                "cached artifacts missing or corrupted in the store (quarantined): "
                f"{', '.join(sorted(bad))}"
            )
        return None


def stage_key(spec: StageSpec, inputs: dict[str, Any]) -> str | None:
    """The cache key Prefect derives for ``spec``'s task called with ``inputs``."""
    import inspect

    try:
        bound = inspect.signature(spec.task.fn).bind(**inputs)
        bound.apply_defaults()  # as Prefect's task parameters
        return spec.task.cache_policy.compute_key(None, dict(bound.arguments), {})
    except Exception:  # diagnostics and checks only: Prefect reports its own errors
        return None


class DirectRunner(_Recorder):
    """Call each stage's adapter function directly, without Prefect (no caching).

    ``outputs`` maps stage name to :class:`StageOutput`, ``seconds`` to its
    wall time.
    """

    def __init__(self, patient_id: str = "", total: int = 0) -> None:
        super().__init__(patient_id, total)
        self.seconds: dict[str, float] = {}

    def run(self, spec: StageSpec, **inputs: Any) -> StageOutput:
        """Call the stage's function and time it."""
        self.started(spec.name)
        t0 = time.perf_counter()
        out = spec.task.fn(**inputs)
        wall = time.perf_counter() - t0
        self.seconds[spec.name] = wall
        return self.finished(out, cached=False, wall=wall)
