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
keys hold) and the versions of :data:`tumor3d.storage.versions.NUMERICAL_PACKAGES`.
Workers that join after the check are not asked.
"""

from __future__ import annotations

import os
import uuid
from pathlib import Path
from typing import Any

from tumor3d.flows.dask_runner import CONNECT_TIMEOUT_S, ClusterError

__all__ = ["PROBE_DIR", "check_workers", "worker_view"]

#: The probe's folder inside the artifact store (removed after the check).
PROBE_DIR = ".tumor3d-probe"


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return f"{type(exc).__name__}: {text.splitlines()[0]}" if text else type(exc).__name__


def _code() -> dict[str, Any]:
    """The stage code digests and numerical package versions of the calling process."""
    from tumor3d.storage.versions import NUMERICAL_PACKAGES, installed_version
    from tumor3d.tasks.stages import STAGES

    dists = sorted({d for names in NUMERICAL_PACKAGES.values() for d in names})
    return {
        "stages": {name: spec.code_digest for name, spec in STAGES.items()},
        "packages": {d: installed_version(d) for d in dists},
    }


def worker_view(store_location: str, token: str) -> dict[str, Any]:
    """Run on a worker: does it read the probe ``token`` in the store, and what code it runs.

    Returns
    -------
    dict
        ``store``: ``"ok"`` or why the probe could not be read there; ``stages`` and
        ``packages``: as this machine's (:func:`check_workers` compares them).
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
        store = _first_line(exc)
    return {"store": store, **_code()}


def _write_probe(store_location: str, token: str) -> Any:
    """Write the probe; returns the function that removes it (and any folder it made)."""
    from tumor3d.storage.objectstore import is_url, open_fs

    if is_url(store_location):
        fs, base = open_fs(store_location)
        key = f"{base}/{PROBE_DIR}/{token}"
        fs.pipe_file(key, token.encode())

        def remove_object() -> None:
            try:
                fs.rm_file(key)
            except OSError:
                pass

        return remove_object
    root = Path(store_location)
    folder = root / PROBE_DIR
    made = [p for p in (folder, *folder.parents) if not p.exists()]  # deepest first
    folder.mkdir(parents=True, exist_ok=True)
    probe = folder / token
    probe.write_text(token)

    def remove_file() -> None:
        probe.unlink(missing_ok=True)
        for p in dict.fromkeys((folder, *made)):  # the probe's and those it made, if empty
            try:
                os.rmdir(p)
            except FileNotFoundError:
                continue
            except OSError:  # not empty (the store holds more than the probe): kept
                break

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
    from distributed import Client

    from tumor3d.storage.objectstore import is_url

    location = os.fspath(store_location)
    if not is_url(location):
        location = str(Path(location).resolve())
    token = uuid.uuid4().hex
    remove = _write_probe(location, token)
    try:
        timeout = CONNECT_TIMEOUT_S if timeout_s is None else timeout_s
        with Client(address, timeout=timeout) as client:
            views = client.run(worker_view, location, token, on_error="return")
    except ClusterError:
        raise
    except Exception as exc:  # noqa: BLE001 - the scheduler answered a moment ago
        raise ClusterError(
            f"Dask scheduler {address}: could not ask its workers ({_first_line(exc)})"
        ) from None
    finally:
        remove()
    mine = _code()
    for worker, view in sorted(views.items()):
        where = f"Dask worker {worker}"
        if isinstance(view, BaseException):
            raise ClusterError(
                f"{where}: the check of what it shares with this machine failed "
                f"({_first_line(view)}); every worker must import this project"
            )
        if view["store"] != "ok":
            raise ClusterError(
                f"{where} does not see the artifact store {location} ({view['store']}); "
                "every worker must reach it at the same location: a path shared by every "
                "machine, or s3://"
            )
        stages = sorted(n for n, d in mine["stages"].items() if view["stages"].get(n) != d)
        if stages:
            raise ClusterError(
                f"{where} runs other tumor3d code (stages {', '.join(stages)} differ from "
                "this machine's); install the same version on every worker"
            )
        packages = sorted(d for d, v in mine["packages"].items() if view["packages"].get(d) != v)
        if packages:
            theirs = ", ".join(
                f"{d} {view['packages'].get(d)} there, {mine['packages'][d]} here" for d in packages
            )
            raise ClusterError(
                f"{where} has other numerical packages ({theirs}); install the same versions "
                "on every worker"
            )
    return len(views)
