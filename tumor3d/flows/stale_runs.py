"""Flow runs whose process was killed are set Crashed, not left Running for good.

A command that ends normally, or by Ctrl-C or SIGTERM, reports its flow runs' final
state (:mod:`tumor3d.flows.cli.errors`). One killed outright (``kill -9``, the kernel's
out-of-memory killer, a machine that stopped) cannot: its runs stayed Running on the
server, since they send no heartbeats, and the UI showed them so forever.

Every command's flow runs carry two tags (:func:`process_tags`): this machine's name and
this process's id with its start time. At the start of each command
(:func:`tumor3d.flows.server.prefect_api`), :func:`crash_stale_runs` sets Crashed the
Running flow runs of this machine whose process is gone, with a message that says so.
The start time guards against a process id reused by another process since; runs of
other machines are left alone (their processes cannot be seen from here).
"""

from __future__ import annotations

import os
import socket
from pathlib import Path

__all__ = ["HOST_TAG", "PROCESS_TAG", "crash_stale_runs", "process_tags"]

#: Tag prefix of the machine a flow run's process runs on.
HOST_TAG = "tumor3d-host:"
#: Tag prefix of the process: ``tumor3d-process:<pid>:<start time in clock ticks>``.
PROCESS_TAG = "tumor3d-process:"


def _proc_stat(pid: int) -> list[str]:
    """The fields of ``/proc/<pid>/stat`` after the command's name (Linux), or []."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return []
    # the command name, in parentheses, may hold spaces: the fields after it are plain
    return stat.rsplit(")", 1)[-1].split()


def _start_ticks(pid: int) -> int | None:
    """When process ``pid`` started, in clock ticks since boot (Linux ``/proc``), or None."""
    fields = _proc_stat(pid)
    try:
        return int(fields[19])  # field 22 of proc(5), the 20th after the name
    except (IndexError, ValueError):
        return None


def process_tags() -> tuple[str, str]:
    """The machine's and the process's tags, for the flow runs a command makes.

    >>> host, process = process_tags()
    >>> host.startswith(HOST_TAG) and process.startswith(f"{PROCESS_TAG}{os.getpid()}:")
    True
    """
    pid = os.getpid()
    ticks = _start_ticks(pid)
    return (
        f"{HOST_TAG}{socket.gethostname()}",
        f"{PROCESS_TAG}{pid}:{'' if ticks is None else ticks}",
    )


def _process_gone(tag: str) -> int | None:
    """The process id of a :data:`PROCESS_TAG` tag whose process has ended, else None.

    >>> _process_gone(process_tags()[1]) is None  # this one runs
    True
    """
    pid_text, _, ticks_text = tag.removeprefix(PROCESS_TAG).partition(":")
    try:
        pid = int(pid_text)
    except ValueError:
        return None
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return pid
    except PermissionError:  # another user's process of that id: alive, maybe reused
        pass
    fields = _proc_stat(pid)
    if fields[:1] == ["Z"]:
        return pid  # ended, not yet reaped by its parent
    ticks = _start_ticks(pid)
    if ticks_text and ticks is not None and str(ticks) != ticks_text:
        return pid  # the id was given to another process since
    return None


def crash_stale_runs() -> list[str]:
    """Set Crashed the Running flow runs of this machine whose process has ended.

    Uses the current Prefect API (at most 2 s a request, no retries); returns the names
    of the runs it set.
    """
    from prefect.client.orchestration import get_client
    from prefect.client.schemas.filters import (
        FlowRunFilter,
        FlowRunFilterState,
        FlowRunFilterStateType,
        FlowRunFilterTags,
    )
    from prefect.client.schemas.objects import StateType
    from prefect.settings import (
        PREFECT_API_REQUEST_TIMEOUT,
        PREFECT_CLIENT_MAX_RETRIES,
        temporary_settings,
    )
    from prefect.states import Crashed

    host = process_tags()[0]
    running = FlowRunFilter(
        state=FlowRunFilterState(type=FlowRunFilterStateType(any_=[StateType.RUNNING])),
        tags=FlowRunFilterTags(all_=[host]),
    )
    crashed = []
    quick = {PREFECT_CLIENT_MAX_RETRIES: 0, PREFECT_API_REQUEST_TIMEOUT: 2.0}
    with temporary_settings(updates=quick), get_client(sync_client=True) as client:
        for run in client.read_flow_runs(flow_run_filter=running):
            tags = [t for t in run.tags if t.startswith(PROCESS_TAG)]
            pid = _process_gone(tags[0]) if tags else None
            if pid is None:
                continue
            message = (
                f"its process ({pid} on {host.removeprefix(HOST_TAG)}) ended without "
                "reporting: killed (kill -9, out of memory) or the machine stopped; found by "
                "a later tumor3d command"
            )
            client.set_flow_run_state(run.id, Crashed(message=message), force=True)
            crashed.append(run.name)
    return crashed
