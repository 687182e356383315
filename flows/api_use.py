"""Which Prefect API a command or a Python call uses, and the tags of its flow runs.

A command (:func:`prefect_api`): ``PREFECT_API_URL`` if configured, else the running
background server, else a temporary server of its own (:mod:`tumor3d.flows.server`
describes both), watched while the command runs (:mod:`tumor3d.flows.server_watch`).
A Python call (:func:`api_of_python_call`): a configured API, else the background
server, else this process's temporary server for Python calls
(:func:`python_call_server`). Either way the flow runs are tagged with this machine and
process, after the Running runs of a killed one are set Crashed
(:mod:`tumor3d.flows.stale_runs`).

The servers' own functions are called through their module (``server.server_status``,
``server._spawn``, ...), so that one definition is what every caller, and a test that
replaces it, reaches.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

from tumor3d.flows import server
from tumor3d.flows.server import ServerError
from tumor3d.flows.server_watch import _watch_server

__all__ = [
    "api_of_python_call",
    "check_configured_api",
    "prefect_api",
    "python_call_server",
    "quick_client",
    "stop_python_call_server",
]


def _configured_api_url() -> str | None:
    """The Prefect API the user configured, if any.

    Not one that a Python call made the process's (:data:`_PROCESS_APIS`; its server may
    have stopped since).
    """
    from prefect.settings import PREFECT_API_URL

    url = PREFECT_API_URL.value() or None
    return None if url in _PROCESS_APIS else url


def check_configured_api(timeout_s: float = 5.0) -> None:
    """Refuse, in one line, a ``PREFECT_API_URL`` that does not answer ``/health``.

    Called before any work (nothing is created for a run that cannot start);
    does nothing when no API is configured (the background or a temporary
    server is used then).

    Raises
    ------
    ServerError
        Naming the URL and what to do (exit code 3 on the command line).
    """
    url = _configured_api_url()
    if url and not server.healthy(url, timeout_s=timeout_s):
        raise ServerError(
            f"the Prefect API {url} (PREFECT_API_URL) does not answer {url.rstrip('/')}/health: "
            "start that server, or unset PREFECT_API_URL to use `tumor3d server start`'s "
            "or a temporary one"
        )


def _drain_prefect_workers() -> None:
    """Send the buffered logs and events before the server they go to stops."""
    from prefect.events.worker import EventsWorker
    from prefect.logging.handlers import APILogWorker

    with contextlib.suppress(Exception):
        APILogWorker.drain_all(timeout=10)
    with contextlib.suppress(Exception):
        EventsWorker.drain_all(timeout=10)


@contextlib.contextmanager
def _use_api(api_url: str, *, drain: bool) -> Iterator[None]:
    import prefect.context
    from prefect.settings import PREFECT_API_URL, temporary_settings

    with temporary_settings(updates={PREFECT_API_URL: api_url}):
        # threads that did not copy this context see the same settings
        global_ctx = getattr(prefect.context, "_temporary_global_settings_context", None)
        with (
            global_ctx(prefect.context.get_settings_context())
            if global_ctx
            else contextlib.nullcontext()
        ):
            try:
                yield
            finally:
                if drain:  # a temporary server stops next: send what is buffered first
                    _drain_prefect_workers()


@contextlib.contextmanager
def api_of_python_call() -> Iterator[None]:
    """The Prefect API of a flow run from Python (``run_patient``, ``run_cohort``, ...).

    A configured ``PREFECT_API_URL`` (a command's :func:`prefect_api`, a user's) is
    used as it is; else the running background server (``tumor3d server start``), as
    the commands use it: Prefect's own temporary server would open the same database
    beside it (a notebook saw "database is locked" tracebacks); else this process's
    temporary server (:func:`python_call_server`: started by the first call, stopped at
    exit, and by itself when the process is killed). No watch: a notebook's process is
    not ended for a server.

    Its flow runs are tagged with this process, as a command's are, and the Running runs
    of a killed process are set Crashed first (:func:`_this_process_once`: at most once a
    minute per API in a process that calls in a loop): a notebook's kernel killed
    mid-cohort left its runs Running on a persistent server for good.

    Outside a command (whose console drops every run record), Prefect's console does
    not show, while the call runs, the tracebacks of its runs that failed on a bad input,
    which the call raises as one line
    (:func:`~tumor3d.flows.quiet_logs.own_failure_tracebacks_off`).
    """
    from tumor3d.flows.quiet_logs import own_failure_tracebacks_off

    in_a_command = _in_a_command()
    with contextlib.nullcontext() if in_a_command else own_failure_tracebacks_off():
        configured = _configured_api_url()
        if configured:
            if not in_a_command:
                check_configured_api()  # one line naming PREFECT_API_URL, before any run
            with _this_process_once(configured):
                yield
            return
        status = server.server_status()
        if status.state == "running" and status.info is not None:
            # drained at the end of each call: what a notebook's run buffered is sent to
            # this server now, not at the process's exit to a server stopped since (a
            # notebook that stopped and started it again spent 4 min at exit retrying the
            # old one, and its next calls' events went there)
            bg = status.info.api_url
            try:
                with _process_api(bg, ui=True), _this_process_once(bg):
                    yield
            finally:
                _drain_prefect_workers()
            return
        # no drain per call: this server stops at exit only, after Prefect's own senders
        # have sent what they hold (concurrent calls waited for each other's events and
        # printed Prefect's "Still processing items")
        api_url = python_call_server()
        with _process_api(api_url, ui=False), _this_process_once(api_url):
            yield


#: The APIs that Python calls made the process's (:func:`_process_api`): never a user's.
_PROCESS_APIS: set[str] = set()
_PROCESS_API_LOCK = threading.Lock()


@contextlib.contextmanager
def _process_api(api_url: str, *, ui: bool) -> Iterator[None]:
    """A Python call's body against ``api_url``, the process's API from then on.

    The process-global settings are set, not swapped and restored per call: concurrent
    calls from threads restored each other's in the wrong order, leaving a stopped
    server's URL as if configured. Prefect's senders and the threads that copy no
    context read the global; the call's own settings context holds the URL too (a
    caller inside ``temporary_settings`` does not see the global). ``ui``: the server
    has a UI (the background server); else no "View at" link is printed.
    """
    from prefect.settings import PREFECT_API_URL, PREFECT_UI_URL, temporary_settings

    updates: dict[Any, Any] = {PREFECT_API_URL: api_url}
    if not ui:
        updates[PREFECT_UI_URL] = ""
    _set_process_api(updates, restore_ui=ui)
    with temporary_settings(updates=updates, restore_defaults=[] if not ui else [PREFECT_UI_URL]):
        yield


def _set_process_api(updates: dict[Any, Any], *, restore_ui: bool) -> None:
    """Make ``updates`` (the API URL, maybe the UI's) the process's global Prefect settings."""
    import prefect.context
    from prefect.settings import PREFECT_API_URL, PREFECT_UI_URL

    with _PROCESS_API_LOCK:
        current = prefect.context.GLOBAL_SETTINGS_CONTEXT
        url = updates[PREFECT_API_URL]
        _PROCESS_APIS.add(url)
        if current.settings.api.url == url:
            return
        _PROCESS_API_BEFORE.setdefault("context", current)
        settings = current.settings.copy_with_update(
            updates=updates, restore_defaults=[PREFECT_UI_URL] if restore_ui else []
        )
        prefect.context.GLOBAL_SETTINGS_CONTEXT = prefect.context.SettingsContext(
            profile=current.profile, settings=settings
        )


#: The process's global settings before a Python call first set them.
_PROCESS_API_BEFORE: dict[str, Any] = {}


#: This process's temporary server for Python calls (:func:`python_call_server`).
_CALL_SERVER: dict[str, Any] = {}
_CALL_SERVER_LOCK = threading.Lock()
#: The one thread that spawns it (:func:`_spawn_from_a_lasting_thread`), and its requests.
_SPAWNER: dict[str, Any] = {}
_SPAWNER_LOCK = threading.Lock()


def _forget_call_server_in_child() -> None:
    """A forked child has neither the parent's server threads nor its locks' holders."""
    global _CALL_SERVER_LOCK, _SPAWNER_LOCK, _PROCESS_API_LOCK
    _CALL_SERVER.pop("proc", None)  # the parent's: its URL stays known as not the user's
    _SPAWNER.clear()
    _CALL_SERVER_LOCK, _SPAWNER_LOCK = threading.Lock(), threading.Lock()
    _PROCESS_API_LOCK = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_call_server_in_child)


def python_call_server() -> str:
    """The API of this process's temporary server for Python calls, started on first use.

    A notebook's calls with no configured API and no background server share one
    server, started by the first (a few seconds) and stopped when the process exits,
    as Prefect's own temporary server was. Unlike Prefect's, it is the commands'
    temporary server (:func:`tumor3d.flows.server._spawn`: ephemeral, no telemetry,
    ``--parent``): it stops itself when its process dies, even by ``kill -9``
    (Prefect's outlived a killed kernel). It is spawned from a thread of its own that
    lives as long as the process: ``PR_SET_PDEATHSIG`` fires when the *thread* that
    spawned the child exits, so a call made from a short-lived thread would otherwise
    take the server down after it. Its own session: a Ctrl-C in a script's terminal
    interrupts the script, not the server. A server found dead (its process ended) is
    started again.

    The calls make its API the process's Prefect API (:func:`_process_api`), so the
    user's own flows use it too instead of starting Prefect's beside it on the same
    database; no UI link is printed (the server has no UI).

    Raises
    ------
    ServerError
        When it does not become healthy in time (the process is then stopped).
    """
    with _CALL_SERVER_LOCK:
        proc, api_url = _CALL_SERVER.get("proc"), _CALL_SERVER.get("api_url")
        if proc is not None and proc.poll() is None:
            return str(api_url)
        port = server._free_port()
        api_url = f"http://127.0.0.1:{port}/api"
        proc = _spawn_from_a_lasting_thread(port)
        try:
            server._wait_healthy(proc, api_url, server._startup_timeout_s())
        except BaseException:
            server._terminate(proc.pid, grace_s=5.0)
            raise
        if not _CALL_SERVER:
            import atexit

            atexit.register(stop_python_call_server)
        _CALL_SERVER.update(proc=proc, api_url=api_url)
        return api_url


def stop_python_call_server() -> None:
    """Stop this process's server for Python calls, if it runs (at exit, or by hand).

    At exit, a server still being started by another thread is left to its watchdog
    (it stops when the process has gone) rather than waited for.
    """
    if not _CALL_SERVER_LOCK.acquire(timeout=5.0):
        return
    try:
        proc = _CALL_SERVER.get("proc")
        if proc is not None and proc.poll() is None:
            _drain_prefect_workers()
            server._terminate(proc.pid, grace_s=5.0)
        _CALL_SERVER.pop("proc", None)
        _restore_process_api(_CALL_SERVER.get("api_url"))
    finally:
        _CALL_SERVER_LOCK.release()


def _restore_process_api(api_url: str | None) -> None:
    """The process's settings as before the first call, if they still name ``api_url``."""
    import prefect.context

    with _PROCESS_API_LOCK:
        before = _PROCESS_API_BEFORE.get("context")
        current = prefect.context.GLOBAL_SETTINGS_CONTEXT
        if before is not None and api_url and current.settings.api.url == api_url:
            prefect.context.GLOBAL_SETTINGS_CONTEXT = before


def _spawn_from_a_lasting_thread(port: int) -> subprocess.Popen:
    """Spawn a Python call's server from the one spawner thread, which never ends.

    (:func:`tumor3d.flows.server._spawn`, in a thread of its own: see
    :func:`python_call_server`.)
    """
    import queue

    with _SPAWNER_LOCK:
        thread = _SPAWNER.get("thread")
        if thread is None or not thread.is_alive():
            requests: queue.Queue = queue.Queue()

            def spawner() -> None:
                while True:
                    at, reply = requests.get()
                    try:
                        reply.put(server._spawn(
                            at, parent=os.getpid(), ephemeral=True, log=None, new_session=True
                        ))  # fmt: skip
                    except BaseException as exc:  # handed to the caller
                        reply.put(exc)

            thread = threading.Thread(target=spawner, name="tumor3d-call-server", daemon=True)
            _SPAWNER.update(thread=thread, requests=requests)
            thread.start()
        requests = _SPAWNER["requests"]
    reply: queue.Queue = queue.Queue(maxsize=1)
    requests.put((port, reply))
    try:
        got = reply.get()
    except BaseException:  # a Ctrl-C while it starts: stop the server the spawner hands over
        threading.Thread(target=_stop_late, args=(reply,), daemon=True).start()
        raise
    if isinstance(got, BaseException):
        raise got
    return got


def _stop_late(reply: Any) -> None:
    """Terminate the server a spawner reply brings after its caller has given up."""
    with contextlib.suppress(Exception):
        got = reply.get(timeout=60)
        if isinstance(got, subprocess.Popen):
            server._terminate(got.pid, grace_s=5.0)


@contextlib.contextmanager
def prefect_api(
    on_temporary_start: Callable[[], None] | None = None, *, services: bool = False
) -> Iterator[str]:
    """Run the body against a Prefect API; yields where it is (see the module docstring).

    ``on_temporary_start`` is called (to print a message) only when a
    temporary server is really started. That server runs no services
    (ephemeral) unless ``services``: a deployment served on it needs the
    scheduler, which makes the runs of its schedule. While the body runs, a server that
    goes away (nothing listens on its port any more: killed, stopped) ends
    the command with one line and exit code 3 (:func:`_watch_server`)
    instead of minutes of Prefect's retries and tracebacks.
    """
    token = _IN_A_COMMAND.set(True)
    try:
        with _command_api(on_temporary_start, services=services) as api_url:
            yield api_url
    finally:
        _IN_A_COMMAND.reset(token)


@contextlib.contextmanager
def _command_api(on_temporary_start: Callable[[], None] | None, *, services: bool) -> Iterator[str]:
    """:func:`prefect_api`'s choice of API, in the order of the module docstring."""
    configured = _configured_api_url()
    if configured:
        check_configured_api()
        with _watch_server(configured), _this_process():
            yield configured
        return
    status = server.server_status()
    if status.state == "running" and status.info is not None:
        # its clients were made for this URL: they drain at exit on their own
        with (
            _use_api(status.info.api_url, drain=False),
            _watch_server(status.info.api_url),
            _this_process(),
        ):
            yield status.info.api_url
        return
    if on_temporary_start is not None:
        on_temporary_start()
    port = server._free_port()
    api_url = f"http://127.0.0.1:{port}/api"
    proc = server._spawn(port, parent=os.getpid(), ephemeral=not services, log=None)
    try:
        server._wait_healthy(proc, api_url, server._startup_timeout_s())
        with _use_api(api_url, drain=True), _watch_server(api_url, server=proc), _this_process():
            yield api_url
    finally:
        if proc.poll() is None:  # (the watch may have reaped it: its pid is then free)
            server._terminate(proc.pid, grace_s=5.0)


#: Seconds a best-effort request to the Prefect API may take (:func:`quick_client`).
QUICK_REQUEST_S = 2.0


@contextlib.contextmanager
def quick_client() -> Iterator[Any]:
    """A synchronous Prefect client that gives up at once (no retries, short requests).

    At most :data:`QUICK_REQUEST_S` a request. For the best-effort state reports that
    must never hold a command up: an interrupted command's runs set Crashed
    (:mod:`tumor3d.flows.cli.errors`), a killed one's found by the next
    (:mod:`tumor3d.flows.stale_runs`); a server stopped by the same Ctrl-C refuses at
    once.
    """
    from prefect.client.orchestration import get_client
    from prefect.settings import (
        PREFECT_API_REQUEST_TIMEOUT,
        PREFECT_CLIENT_MAX_RETRIES,
        temporary_settings,
    )

    quick = {PREFECT_CLIENT_MAX_RETRIES: 0, PREFECT_API_REQUEST_TIMEOUT: QUICK_REQUEST_S}
    with temporary_settings(updates=quick), get_client(sync_client=True) as client:
        yield client


@contextlib.contextmanager
def _this_process(*, sweep: bool = True) -> Iterator[None]:
    """Tag the body's flow runs with this machine and process, after crashing stale runs.

    The Running runs of a killed command of this machine are set Crashed first, unless
    not ``sweep`` (:mod:`tumor3d.flows.stale_runs`; the runs of every server share
    Prefect's database).
    """
    from prefect import tags

    from tumor3d.flows.stale_runs import crash_stale_runs, process_tags

    if sweep:
        with contextlib.suppress(Exception):  # best effort: never in the command's way
            crash_stale_runs()
    with tags(*process_tags()):
        yield


#: Set inside a command's :func:`prefect_api` (also where processes carry no tags).
_IN_A_COMMAND: contextvars.ContextVar[bool] = contextvars.ContextVar(
    "tumor3d_in_a_command", default=False
)


def _in_a_command() -> bool:
    """Whether the caller runs inside a command's :func:`prefect_api` (or its runs' tags)."""
    from prefect.context import TagsContext

    from tumor3d.flows.stale_runs import PLACE_TAG

    if _IN_A_COMMAND.get():
        return True
    return any(t.startswith(PLACE_TAG) for t in TagsContext.get().current_tags)


#: Seconds between two sweeps of one API by the Python calls of one process.
PYTHON_SWEEP_PERIOD_S = 60.0
#: API URL -> when this process's Python calls last swept it (time.monotonic()).
_python_sweeps: dict[str, float] = {}


@contextlib.contextmanager
def _this_process_once(api_url: str) -> Iterator[None]:
    """:func:`_this_process` for a Python call, unless inside it already (a command's).

    It sweeps ``api_url`` at most every :data:`PYTHON_SWEEP_PERIOD_S` (a notebook's
    loop of a thousand ``run_patient`` calls would pay ~0.1 s each).
    """
    if _in_a_command():
        yield
        return
    now = time.monotonic()
    last = _python_sweeps.get(api_url)
    sweep = last is None or now - last >= PYTHON_SWEEP_PERIOD_S
    if sweep:
        _python_sweeps[api_url] = now
    with _this_process(sweep=sweep):
        yield
