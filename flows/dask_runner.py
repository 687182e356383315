"""Task runners of the cohort flow: local threads (default) or a Dask cluster.

Wiring only. :func:`cohort_task_runner` picks the task runner that
:func:`tumor3d.flows.cohort.cohort_flow` submits its stages to:

* default -- Prefect's ``ThreadPoolTaskRunner`` (``workers`` threads in the
  flow's process);
* ``dask_workers=N`` -- a temporary ``distributed.LocalCluster`` of ``N``
  worker processes, one thread each, through ``prefect-dask``'s
  ``DaskTaskRunner``;
* ``dask_address="tcp://HOST:PORT"`` -- an existing Dask scheduler.

The scheduler is contacted *before* any patient starts
(:func:`check_scheduler`): an unreachable address is a one-line
:class:`ClusterError`, which the CLI prints with exit code 3 (environment error). Every worker must
see the artifact store at the same location (a shared path or an ``s3://``
URL) and import this project (same code, same ``PYTHONPATH``).
"""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import time
from typing import Any

from tumor3d.errors import InputError, Tumor3DError
from tumor3d.flows.dask_check import connect_once
from tumor3d.flows.quiet_logs import console_is_quiet
from tumor3d.storage.product_memo import MEMO_ENV

__all__ = [
    "ClusterError",
    "DaskSpec",
    "EagerDaskTaskRunner",
    "WORKER_PRODUCT_MEMO_MIB",
    "check_scheduler",
    "cohort_task_runner",
]

try:  # the optional extra ``tumor3d[dask]``
    from prefect_dask import DaskTaskRunner as _DaskTaskRunner
except ImportError:  # pragma: no cover - without the extra
    _DaskTaskRunner = None

#: Seconds to wait for a Dask scheduler to answer before giving up.
CONNECT_TIMEOUT_S = 10.0
#: Seconds beyond it before a connection that hangs (no scheduler behind it) is given up.
CONNECT_GRACE_S = 5.0

#: A scheduler that answered within this many seconds is not asked again, once: the
#: command's preflight and the cohort it then starts each check the address (a child
#: process and a connection each, about 1 s); the second check takes the first's answer.
RECENT_CHECK_S = 30.0

#: address -> (time.monotonic() of its last answer, its workers then)
_answered: dict[str, tuple[float, int]] = {}

#: MiB of decoded volumes a local cluster's worker process keeps
#: (:mod:`tumor3d.storage.product_memo`; about one patient's stage volumes), unless
#: ``TUMOR3D_PRODUCT_MEMO_MIB`` is set. The flow's own process keeps 256 and forgets
#: each patient once published.
WORKER_PRODUCT_MEMO_MIB = 64


class ClusterError(Tumor3DError):
    """A Dask scheduler that cannot be reached (an environment problem, exit code 3)."""


if _DaskTaskRunner is not None:

    class EagerDaskTaskRunner(_DaskTaskRunner):
        """``DaskTaskRunner`` that connects when the flow starts, not at the first submit.

        The cohort flow submits from several lane threads at once; prefect-dask
        creates its client lazily on first use, so without this two lanes could
        race to create two clusters.
        """

        def __enter__(self) -> EagerDaskTaskRunner:
            super().__enter__()
            _ = self.client
            return self

else:  # pragma: no cover - without the extra
    EagerDaskTaskRunner = None


class DaskSpec:
    """Where the cohort's stages run: a Dask address, a local cluster size, or neither.

    Parameters
    ----------
    address : str, optional
        ``tcp://HOST:PORT`` of an existing scheduler.
    n_workers : int, optional
        Size of a temporary local cluster (worker processes, one thread each).
    processes : bool
        Local cluster workers as processes (default) or threads in this
        process (``False``: faster to start, but the GIL-bound parts of a stage
        then share one interpreter).
    """

    def __init__(
        self,
        address: str | None = None,
        n_workers: int | None = None,
        *,
        processes: bool = True,
    ) -> None:
        if address and n_workers:
            raise InputError("give either --dask-address or --dask-workers, not both")
        if n_workers is not None and (
            isinstance(n_workers, bool) or not isinstance(n_workers, int) or n_workers < 1
        ):
            raise InputError(f"--dask-workers must be an integer >= 1, got {n_workers!r}")
        if address is not None and not str(address).strip():
            raise InputError("--dask-address is empty")
        self.address = address
        self.n_workers = n_workers
        self.processes = processes

    @property
    def enabled(self) -> bool:
        """True when the stages run on Dask."""
        return bool(self.address or self.n_workers)

    def describe(self) -> str:
        """One line for logs and the cohort report."""
        if self.address:
            return f"Dask scheduler {self.address}"
        if self.n_workers:
            kind = "processes" if self.processes else "threads"
            return f"local Dask cluster of {self.n_workers} worker {kind}"
        return "local threads"


def check_scheduler(address: str, *, timeout_s: float | None = None) -> int:
    """Connect to a Dask scheduler once and return its number of workers.

    ``timeout_s`` defaults to :data:`CONNECT_TIMEOUT_S`, read at the call. A scheduler
    that answered in the last :data:`RECENT_CHECK_S` seconds is not asked again by the
    next check (its workers then), but by the one after; one that did not answer is
    asked each time.

    Raises
    ------
    ClusterError
        One line naming the address: nothing answers within ``timeout_s``,
        something that is no Dask scheduler answers (or hangs), or the
        address is malformed.
    """
    try:
        from distributed.comm import get_address_host_port, parse_address
    except ImportError:
        raise InputError(
            "Dask needs the optional dependencies: pip install 'tumor3d[dask]'"
        ) from None
    if timeout_s is None:
        timeout_s = CONNECT_TIMEOUT_S
    recent = _answered.pop(address, None)  # used once
    if recent is not None and time.monotonic() - recent[0] < RECENT_CHECK_S:
        return recent[1]
    fix = "start the scheduler or fix --dask-address"
    try:
        scheme, _ = parse_address(address)
        if scheme != "inproc":
            port = get_address_host_port(address)[1]
            if not 0 < port < 65536:
                raise ValueError(f"port {port} is not between 1 and 65535")
    except ValueError as exc:
        raise ClusterError(
            f"Dask scheduler {address}: not a scheduler address ({exc}); {fix}"
        ) from None
    if scheme == "inproc":  # a cluster of this process (a notebook's): nothing else answers
        found = connect_once(address, timeout_s)
    else:
        found = _connect_in_child(address, timeout_s, fix)
    if "workers" in found:
        _answered[address] = (time.monotonic(), int(found["workers"]))
        return int(found["workers"])
    kind, text = found["error"], found["text"] or found["error"]
    if kind in ("OSError", "TimeoutError") or kind.endswith(("ConnectionError", "CommClosedError")):
        raise ClusterError(
            f"Dask scheduler {address}: cannot connect within {timeout_s:g} s ({text}); {fix}"
        )
    raise ClusterError(
        f"Dask scheduler {address}: what answered is not a Dask scheduler ({kind}: {text}); {fix}"
    )


def _connect_in_child(address: str, timeout_s: float, fix: str) -> dict[str, Any]:
    """:func:`tumor3d.flows.dask_check.connect_once` in a child process, with a deadline.

    A service that accepts the connection but is no Dask scheduler (its dashboard's
    port, a proxy) may never complete the handshake, and its half-made client then
    blocks, and prints, at interpreter exit: the child is killed instead.
    """
    try:
        done = subprocess.run(
            [sys.executable, "-m", "tumor3d.flows.dask_check", address, repr(float(timeout_s))],
            capture_output=True, text=True, timeout=timeout_s + CONNECT_GRACE_S, check=False,
        )  # fmt: skip
    except subprocess.TimeoutExpired:
        raise ClusterError(
            f"Dask scheduler {address}: no answer as a Dask scheduler within {timeout_s:g} s "
            f"(something accepted the connection: the dashboard's port?); {fix}"
        ) from None
    lines = done.stdout.strip().splitlines()
    try:
        return dict(json.loads(lines[-1]))
    except (IndexError, ValueError):
        last = (done.stderr.strip().splitlines() or [f"exit code {done.returncode}"])[-1]
        raise ClusterError(f"Dask scheduler {address}: the check failed ({last}); {fix}") from None


def _dask_runner_class() -> Any:
    if EagerDaskTaskRunner is None:
        raise InputError(
            "Dask needs the optional dependencies: pip install 'tumor3d[dask]' "
            "(prefect-dask, dask, distributed)"
        )
    return EagerDaskTaskRunner


def cohort_task_runner(workers: int, spec: DaskSpec | None = None) -> Any:
    """The task runner for a cohort: threads, a local Dask cluster or a remote scheduler.

    Parameters
    ----------
    workers : int
        Threads of the default runner (patients at a time).
    spec : DaskSpec, optional
        Dask settings; None or disabled gives the thread runner.
    """
    from prefect.task_runners import ThreadPoolTaskRunner

    if spec is None or not spec.enabled:
        return ThreadPoolTaskRunner(max_workers=workers)
    runner_cls = _dask_runner_class()
    # distributed logs every client connection at INFO (prefect-dask opens one per
    # task on the workers): keep them out of the progress display; -v/--verbose
    # or DASK_LOGGING__DISTRIBUTED=info brings them back
    os.environ.setdefault("DASK_LOGGING__DISTRIBUTED", "warning")
    if os.environ.get("PREFECT_LOGGING_LEVEL", "").upper() in ("WARNING", "ERROR", "CRITICAL"):
        logging.getLogger("distributed").setLevel(logging.WARNING)
    if spec.address:
        return runner_cls(address=spec.address)
    cluster_kwargs: dict[str, Any] = {
        "n_workers": spec.n_workers,
        "threads_per_worker": 1,
        "processes": spec.processes,
        # a free port, never 8787: with None the scheduler still tries 8787 and warns
        # when another cluster (a user's, a second cohort) holds it
        "dashboard_address": ":0",
    }
    if spec.processes and console_is_quiet():
        # the workers' Prefect logs reach the command's stderr: as quiet as its own console
        cluster_kwargs["preload"] = ["tumor3d.flows.quiet_logs"]
    if spec.processes and MEMO_ENV not in os.environ:
        # a worker process never publishes, so nothing forgets its volumes: a small bound
        cluster_kwargs["env"] = {MEMO_ENV: str(WORKER_PRODUCT_MEMO_MIB)}
    return runner_cls(cluster_class="distributed.LocalCluster", cluster_kwargs=cluster_kwargs)
