"""What every worker of a Dask scheduler must share with the machine that starts a cohort.

A cohort on an existing scheduler (``--dask-address``) runs its stages on workers that
may be other machines. Each must reach the artifact store at the same location (a
path shared by every machine, or ``s3://``) and run the same stage code with the same
numerical packages. A worker that does not would write artifacts where no other
machine finds them (every patient then fails on a "missing artifact" that names the
symptom, not the cause), or compute stages with other code than the run records in
its provenance. :func:`check_workers` asks every connected worker once, before any
patient starts, and names the first that differs in one line (:class:`ClusterError`,
exit code 3).

Wiring only: the probe is a small file (an object on S3) that this process writes
under ``<store>/.tumor3d-probe/`` and removes again; the code is compared by the
stages' code digests (:attr:`tumor3d.tasks.spec.StageSpec.code_digest`, which the cache
keys hold) and the versions of :data:`tumor3d.storage.versions.NUMERICAL_DISTRIBUTIONS`.
Workers that join after the check are not asked.
"""

from __future__ import annotations

import asyncio
import os
import platform
import threading
import uuid
from pathlib import Path
from typing import Any

from tumor3d.errors import InputError, exception_line
from tumor3d.flows.dask_runner import CONNECT_TIMEOUT_S, ClusterError
from tumor3d.storage.refs import StoreError

__all__ = ["PROBE_DIR", "WORKER_CHECK_TIMEOUT_S", "check_workers", "worker_view"]

#: The probe's folder inside the artifact store (removed after the check).
PROBE_DIR = ".tumor3d-probe"

#: Seconds every worker has to answer, read at the call. A worker's first answer
#: imports the stages and digests their code (2-4 s); a stopped or hung worker, or one
#: whose running task holds the GIL, does not answer and is named.
WORKER_CHECK_TIMEOUT_S = 60.0


def _code() -> dict[str, Any]:
    """The stage code digests and numerical package versions of the calling process."""
    from tumor3d.storage.versions import NUMERICAL_DISTRIBUTIONS, installed_version
    from tumor3d.tasks.stages import code_digests

    return {
        # the code digests are of syntax trees, whose form differs between Python versions
        "python": ".".join(platform.python_version_tuple()[:2]),
        "stages": code_digests(),
        "packages": {d: installed_version(d) for d in NUMERICAL_DISTRIBUTIONS},
    }


def worker_view(store_location: str, token: str) -> dict[str, Any]:
    """Run on a worker: does it read the probe ``token`` in the store, and what code it runs.

    Returns
    -------
    dict
        ``store``: ``"ok"`` or why the probe could not be read there; ``python``
        (major.minor), ``stages`` (code digests) and ``packages`` (versions): as this
        machine's (:func:`check_workers` compares them).
    """
    from tumor3d.storage.objectstore import is_url, open_fs, read_object

    try:
        if is_url(store_location):
            fs, base = open_fs(store_location)
            seen = read_object(fs, f"{base}/{PROBE_DIR}/{token}").decode()
        else:
            seen = (Path(store_location) / PROBE_DIR / token).read_text()
        store = "ok" if seen == token else "the probe there holds other bytes"
    except Exception as exc:  # noqa: BLE001 - any failure is "does not see it", named
        store = exception_line(exc)
    return {"store": store, **_code()}


async def _worker_view_off_the_loop(store_location: str, token: str) -> dict[str, Any]:
    """:func:`worker_view` in a thread of the worker, which is what the check runs there.

    The worker's event loop (heartbeats, other clients) keeps running while the stages
    are imported or the store answers slowly.
    """
    return await asyncio.to_thread(worker_view, store_location, token)


def _write_probe(store_location: str, token: str) -> Any:
    """Write the probe; returns the function that removes it (and any folder it made)."""
    from tumor3d.storage.objectstore import is_url, open_fs

    if is_url(store_location):
        fs, base = open_fs(store_location)
        key = f"{base}/{PROBE_DIR}/{token}"
        try:
            fs.pipe_file(key, token.encode())
        except Exception as exc:  # noqa: BLE001 - botocore/aiohttp raise many types
            raise StoreError(
                f"{store_location}: cannot write in the artifact store ({exception_line(exc)})"
            ) from None

        def remove_object() -> None:
            try:
                fs.rm_file(key)
            except OSError:
                pass

        return remove_object
    root = Path(store_location)
    if root.exists() and not root.is_dir():
        raise InputError("the artifact store must be a folder, but this is a file", root)
    folder = root / PROBE_DIR
    made = [p for p in (folder, *folder.parents) if not p.exists()]  # deepest first
    probe = folder / token

    def remove_file() -> None:
        try:
            probe.unlink()
        except OSError:  # never written, or already gone
            pass
        for p in dict.fromkeys((folder, *made)):  # the probe's and those it made, if empty
            try:
                os.rmdir(p)
            except FileNotFoundError:
                continue
            except OSError:  # not empty (the store holds more than the probe): kept
                break

    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe.write_text(token)
    except OSError as exc:
        remove_file()
        raise StoreError(
            f"{root}: cannot write in the artifact store ({exc.strerror or exception_line(exc)})"
        ) from None
    return remove_file


def check_workers(
    address: str, store_location: str | os.PathLike[str], *, timeout_s: float | None = None
) -> int:
    """Ask every worker of the scheduler at ``address`` whether it shares the run's ground.

    Parameters
    ----------
    address : str
        The scheduler (it answered :func:`tumor3d.flows.dask_runner.check_scheduler`).
    store_location : str or path
        The artifact store: an ``s3://`` URL, or a local path (made absolute here, as
        the stages receive it).

    Returns
    -------
    int
        The number of workers asked.

    Raises
    ------
    ClusterError
        One line naming the first worker that cannot read the store's probe, runs
        other stage code, or has other numerical packages; or that cannot run the
        check (tumor3d not importable there).
    """
    from tumor3d.storage.objectstore import is_url

    location = os.fspath(store_location)
    if not is_url(location):
        location = str(Path(location).resolve())
    token = uuid.uuid4().hex
    remove = _write_probe(location, token)
    try:
        connect_s = CONNECT_TIMEOUT_S if timeout_s is None else timeout_s
        views, silent = _ask_workers(address, location, token, connect_s, WORKER_CHECK_TIMEOUT_S)
    finally:
        remove()
    if silent:
        raise ClusterError(
            f"Dask worker {silent[0]}: no answer within {WORKER_CHECK_TIMEOUT_S:g} s to the "
            "check of the artifact store and the code (stopped, hung, or busy in a task that "
            "holds the GIL)"
        )
    mine = _code()
    for worker, view in sorted(views.items()):
        _judge(f"Dask worker {worker}", view, mine, location)
    return len(views)


def _judge(where: str, view: Any, mine: dict[str, Any], location: str) -> None:
    """Raise :class:`ClusterError` if a worker's answer differs from this machine's."""
    if isinstance(view, BaseException):
        if isinstance(view, ImportError) and "tumor3d" in str(view):
            raise ClusterError(
                f"{where} runs another version of tumor3d ({exception_line(view)}); install "
                "the same version on every worker"
            )
        why = exception_line(view)
        if type(view).__name__ == "CommClosedError":
            raise ClusterError(f"{where} left the cluster during the check ({why})")
        raise ClusterError(f"{where}: the check of what it shares with this machine failed ({why})")
    if view["store"] != "ok":
        raise ClusterError(
            f"{where} does not see the artifact store {location} ({view['store']}); every "
            "worker must reach it at the same location: a path shared by every machine, or s3://"
        )
    if view.get("python") != mine["python"]:
        raise ClusterError(
            f"{where} runs Python {view.get('python')} ({mine['python']} here): the stages' "
            "code digests and cache keys differ between Python versions; run every worker "
            "on the same one"
        )
    stages = sorted(n for n, d in mine["stages"].items() if view["stages"].get(n) != d)
    if stages:
        raise ClusterError(
            f"{where} runs other tumor3d code (stages {', '.join(stages)} differ from this "
            "machine's); install the same version on every worker"
        )
    packages = sorted(d for d, v in mine["packages"].items() if view["packages"].get(d) != v)
    if packages:
        theirs = ", ".join(
            f"{d} {view['packages'].get(d)} there, {mine['packages'][d]} here" for d in packages
        )
        raise ClusterError(
            f"{where} has other numerical packages ({theirs}); install the same versions on "
            "every worker"
        )


def _ask_workers(
    address: str, location: str, token: str, connect_s: float, answer_s: float
) -> tuple[dict[str, Any], list[str]]:
    """Every worker's :func:`worker_view` (or its exception), and the silent workers.

    A worker is silent when it did not answer within ``answer_s``. Asked from a thread
    with its own event loop (a notebook's loop may be running in this one), each worker
    separately, so that a silent one is named while the others' answers stand.
    """
    from distributed import Client

    async def ask() -> tuple[dict[str, Any], list[str]]:
        async with Client(address, asynchronous=True, timeout=connect_s) as client:
            workers = sorted((await client.scheduler.identity())["workers"])
            asked = {
                w: asyncio.ensure_future(
                    client.run(
                        _worker_view_off_the_loop, location, token, workers=[w], on_error="return"
                    )
                )
                for w in workers
            }
            if not asked:
                return {}, []
            done, pending = await asyncio.wait(asked.values(), timeout=answer_s)
            for future in pending:
                future.cancel()
            views = {}
            for w, future in asked.items():
                if future in done:
                    exc = future.exception()
                    views[w] = exc if exc is not None else next(iter(future.result().values()))
            return views, [w for w, future in asked.items() if future in pending]

    outcome: dict[str, Any] = {}

    def run() -> None:
        try:
            outcome["value"] = asyncio.run(ask())
        except BaseException as exc:  # noqa: BLE001 - handed to the caller's thread
            outcome["error"] = exc

    thread = threading.Thread(target=run, name="tumor3d-dask-worker-check", daemon=True)
    thread.start()
    thread.join(connect_s + answer_s + 30.0)  # the loop's own deadlines end it before this
    if thread.is_alive():
        raise ClusterError(
            f"Dask scheduler {address}: no answer within {connect_s + answer_s + 30.0:g} s "
            "while its workers were asked about the artifact store and the code"
        )
    if "error" in outcome:
        exc = outcome["error"]
        if isinstance(exc, ClusterError | KeyboardInterrupt):
            raise exc
        raise ClusterError(
            f"Dask scheduler {address}: could not ask its workers ({exception_line(exc)})"
        ) from None
    return outcome["value"]
