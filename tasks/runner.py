"""Runners: how a flow executes one stage.

A runner's ``run(spec, **inputs)`` executes the stage declared by ``spec``
and returns its :class:`~tasks.spec.StageOutput`; :attr:`runs` records how
each went (:class:`StageRun`).

* :class:`PrefectRunner` *submits* the stage's cached Prefect task to the
  current flow's task runner (``task.submit``, a Prefect future), so the
  flow's task runner decides where it executes (threads by default; a Dask
  task runner can be plugged into the flow without changing any stage). It
  keeps Prefect's results in the artifact store's ``prefect-results`` folder
  and repairs cache hits that cannot be trusted: a cached result whose
  artifacts are gone from the store or fail their digest check
  (:meth:`~storage.store.ArtifactStore.verify`, which quarantines a corrupted
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

from storage.store import ArtifactStore
from tasks.progress import ProgressEvent, report
from tasks.spec import StageOutput, StageSpec

__all__ = ["DirectRunner", "PrefectRunner", "StageRun", "result_storage_for"]

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

    For a local store, a path (Prefect makes it a local file system), so no
    storage block has to be registered on the server. For an object store
    (:class:`storage.objectstore.ObjectStore`), a Prefect ``RemoteFileSystem``
    block on ``<url>/prefect-results``, saved on the Prefect server once per
    process as ``tumor3d-results-<hash of the URL>`` (Prefect requires result
    storage blocks to be saved, and every Dask worker then reads the same
    cache).
    """
    url = getattr(store, "url", None)
    if url is not None:
        return _remote_result_storage(url, store.storage_options)  # type: ignore[union-attr]
    root = store.root if isinstance(store, ArtifactStore) else store
    path = Path(root).resolve() / "prefect-results"
    path.mkdir(parents=True, exist_ok=True)
    return path


_REMOTE_STORAGE: dict[str, Any] = {}


def _remote_result_storage(url: str, options: dict[str, Any]) -> Any:
    from prefect.filesystems import RemoteFileSystem
    from prefect.settings import PREFECT_API_URL

    key = f"{PREFECT_API_URL.value()}|{url}"  # saved on this server
    with _TASKS_LOCK:
        block = _REMOTE_STORAGE.get(key)
        if block is None:
            block = RemoteFileSystem(basepath=f"{url}/prefect-results", settings=options)
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
        task = _task_for(spec, self.result_storage, refresh, self.patient_id)
        future = task.submit(**inputs)
        future.wait()
        wrapped = getattr(future, "wrapped_future", None)
        if wrapped is not None and getattr(wrapped, "status", None) == "error":
            # Dask itself gave up (KilledWorker: every worker that ran it died): the task
            # run never finished, so its Prefect state says Pending/Running; name the cause
            raise wrapped.exception()
        return future.state

    def _record_bytes(self, spec: StageSpec, inputs: dict[str, Any]) -> bytes | None:
        """The cached result record this stage's key names, if present (before submitting)."""
        try:
            key = spec.task.cache_policy.compute_key(None, inputs, {})
            return (self.result_storage / key).read_bytes() if key else None
        except Exception:  # diagnostics only: never fail a stage for it
            return None

    def run(self, spec: StageSpec, **inputs: Any) -> StageOutput:
        """Run one stage (cached), repairing an untrustworthy cache hit."""
        self.started(spec.name)
        t0 = time.perf_counter()
        record = self._record_bytes(spec, inputs)
        state = self._submit(spec, refresh=False, **inputs)
        cached = state.name == "Cached"
        repaired = missed = None
        if not cached and record is not None:
            # Issue 6's intermittent miss: Prefect's ResultStore.exists() swallows any
            # error reading a record and reports a miss; name it instead of nothing.
            missed = _why_prefect_missed(record)
            _log.warning("%s: recomputed although its cache record existed: %s", spec.name, missed)
        try:
            out: StageOutput = state.result()
        except Exception as exc:
            if not cached:
                raise
            out, repaired = None, f"cached result unreadable ({type(exc).__name__})"  # type: ignore[assignment]
        if cached and repaired is None:
            repaired = self._distrust(out)
        if repaired is not None:
            _log.warning("%s: %s; recomputing", spec.name, repaired)
            out = self._submit(spec, refresh=True, **inputs).result()
            cached = False
        wall = time.perf_counter() - t0
        return self.finished(out, cached=cached, wall=wall, repaired=repaired or missed)

    def _distrust(self, out: Any) -> str | None:
        """Why a cached output cannot be used, or None if it can."""
        if not isinstance(out, StageOutput):
            return f"cached result is a {type(out).__name__}, not a StageOutput"
        if not out.verify():
            return "cached result failed its digest check (edited or corrupted)"
        # verify(): present AND content matching its digest; a corrupted object is
        # quarantined by the store, so recomputing the stage writes it afresh
        bad = [k for k, r in out.artifacts.items() if not self.store.verify(r)]
        if bad:
            return (
                "cached artifacts missing or corrupted in the store (quarantined): "
                f"{', '.join(sorted(bad))}"
            )
        return None


def _why_prefect_missed(record: bytes) -> str:
    """Why Prefect may have ignored a present result record (it hides the reason)."""
    from prefect.results import ResultRecord

    try:
        rec = ResultRecord.deserialize(record)
    except Exception as exc:
        first = (str(exc).strip().splitlines() or [""])[0][:200]
        return f"cache record present but unreadable by Prefect ({type(exc).__name__}: {first})"
    expiration = getattr(rec.metadata, "expiration", None)
    return f"cache record present and readable (expiration {expiration}); Prefect missed it"


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
