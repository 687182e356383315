"""Flow runs whose process was killed are set Crashed, not left Running for good.

A command that ends normally, or by Ctrl-C or SIGTERM, reports its flow runs' final
state (:mod:`tumor3d.flows.cli.errors`). One killed outright (``kill -9``, the kernel's
out-of-memory killer, a machine that stopped) cannot: its runs stayed Running on the
server, since they send no heartbeats, and the UI showed them so forever.

Every command's flow runs carry two tags (:func:`process_tags`): where its processes
are seen, and this process's id with its start time. Where is this boot of this
machine's kernel and its process-id namespace (``/proc/sys/kernel/random/boot_id`` and
the inode of ``/proc/self/ns/pid``), not the host name, which containers and cloned
machines share. At the start of each command (:func:`tumor3d.flows.api_use.prefect_api`),
:func:`crash_stale_runs` sets Crashed the Running flow runs tagged with this place whose
process is gone, with a message that says so. The start time guards against a process
id reused by another process since; runs of other places are left alone (their
processes cannot be seen from here), and without ``/proc`` (macOS) nothing is tagged or
swept. A run that has just ended is never overwritten (no forced state).
"""

from __future__ import annotations

import os
import socket
import time
from pathlib import Path

__all__ = ["PLACE_TAG", "PROCESS_TAG", "crash_stale_runs", "process_tags"]

#: Tag prefix of where a flow run's process is seen: ``tumor3d-place:<boot id>:<pid ns>``.
PLACE_TAG = "tumor3d-place:"
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
    return _ticks_of(_proc_stat(pid))


def _ticks_of(fields: list[str]) -> int | None:
    """The start time in :func:`_proc_stat`'s fields, or None."""
    try:
        return int(fields[19])  # field 22 of proc(5), the 20th after the name
    except (IndexError, ValueError):
        return None


def _place() -> str | None:
    """The tag of this kernel boot and process-id namespace, or None without ``/proc``."""
    try:
        boot = Path("/proc/sys/kernel/random/boot_id").read_text().strip()
        namespace = os.stat("/proc/self/ns/pid").st_ino
    except OSError:
        return None
    return f"{PLACE_TAG}{boot}:{namespace}" if boot else None


def process_tags() -> tuple[str, ...]:
    """The place's and the process's tags for the flow runs a command makes.

    None without ``/proc``: a process there cannot be told apart from another.

    >>> tags = process_tags()
    >>> not tags or (tags[0].startswith(PLACE_TAG)
    ...              and tags[1].startswith(f"{PROCESS_TAG}{os.getpid()}:"))
    True
    """
    place, pid = _place(), os.getpid()
    ticks = _start_ticks(pid)
    if place is None or ticks is None:
        return ()
    return place, f"{PROCESS_TAG}{pid}:{ticks}"


def _process_gone(tag: str) -> int | None:
    """The process id of a :data:`PROCESS_TAG` tag whose process has ended, else None.

    >>> _process_gone(f"{PROCESS_TAG}{os.getpid()}:{_start_ticks(os.getpid())}") is None
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
    ticks = _ticks_of(fields)
    if ticks_text and ticks is not None and str(ticks) != ticks_text:
        return pid  # the id was given to another process since
    return None


def crash_stale_runs(limit: int = 200, deadline_s: float = 5.0) -> list[str]:
    """Set Crashed the Running flow runs of this place whose process has ended.

    Uses the current Prefect API (at most 2 s a request, no retries), on at most
    ``limit`` Running runs, and sets no more once ``deadline_s`` have passed (a slow
    server holds a command up for seconds, not minutes; the next command goes on);
    returns the names of the runs it set. A run that ended since it was read keeps its
    final state (the server refuses Crashed after it).
    """
    from prefect.client.schemas.filters import (
        FlowRunFilter,
        FlowRunFilterState,
        FlowRunFilterStateType,
        FlowRunFilterTags,
    )
    from prefect.client.schemas.objects import StateType
    from prefect.client.schemas.responses import SetStateStatus
    from prefect.states import Crashed

    from tumor3d.flows.api_use import quick_client

    place = _place()
    if place is None:
        return []
    running = FlowRunFilter(
        state=FlowRunFilterState(type=FlowRunFilterStateType(any_=[StateType.RUNNING])),
        tags=FlowRunFilterTags(all_=[place]),
    )
    crashed = []
    deadline = time.monotonic() + deadline_s
    with quick_client() as client:
        for run in client.read_flow_runs(flow_run_filter=running, limit=limit):
            if time.monotonic() > deadline:
                break
            tags = [t for t in run.tags if t.startswith(PROCESS_TAG)]
            pid = _process_gone(tags[0]) if tags else None
            if pid is None:
                continue
            message = (
                f"its process ({pid} on {socket.gethostname()}) ended without reporting: "
                "killed (kill -9, out of memory) or the machine stopped; found by a later "
                "tumor3d command"
            )
            result = client.set_flow_run_state(run.id, Crashed(message=message))
            if result.status == SetStateStatus.ACCEPT:
                crashed.append(run.name)
    return crashed
