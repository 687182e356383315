"""The local Prefect server the commands talk to: a background one, or a temporary one.

Which Prefect API a command uses (:func:`prefect_api`), in order:

1. ``PREFECT_API_URL``, when the environment or the Prefect profile sets it
   (the user's own server, Prefect Cloud, the test harness): used as is.
2. The **background server** of ``tumor3d server start``, when its state file
   names a live process that answers ``/api/health``.
3. Otherwise a **temporary server** is started for this command (the
   "starting Prefect" message is printed only then) and stopped when the
   command ends. It is a child process that watches its parent: on Linux the
   kernel sends it SIGTERM when the command dies (``prctl(PR_SET_PDEATHSIG)``),
   and on every platform a watchdog thread polls ``os.getppid()`` and stops it,
   so a ``kill -9`` of the command never leaves an orphaned server behind.

State folder: ``$TUMOR3D_HOME``, default ``~/.tumor3d``. The background
server's state is ``server.json`` there (pid, port, API URL, log file, start
time) and its log ``server.log``. A state file whose process is gone (a reboot,
a ``kill -9``) is stale: ``status`` says so and ``start``/``stop`` remove it.
Both servers use Prefect's own database under ``PREFECT_HOME`` (default
``~/.prefect``), so runs made with either appear in the UI of the background
server (``http://127.0.0.1:PORT``).

The server process itself is ``python -m tumor3d.flows.server --port P [--parent PID]
[--ephemeral]``: uvicorn serving ``prefect.server.api.server:create_app``, the
app Prefect's own ``prefect server start`` and ephemeral server serve.
"""

from __future__ import annotations

import argparse
import codecs
import contextlib
import contextvars
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from tumor3d.errors import Tumor3DError

__all__ = [
    "SERVER_MODULE",
    "STATE_ENV",
    "ServerError",
    "ServerInfo",
    "ServerStatus",
    "check_configured_api",
    "healthy",
    "prefect_api",
    "server_status",
    "start_server",
    "state_dir",
    "stop_server",
]

#: Environment variable naming the state folder (default ``~/.tumor3d``).
STATE_ENV = "TUMOR3D_HOME"
#: The module run as the server process (``python -m tumor3d.flows.server``).
SERVER_MODULE = "tumor3d.flows.server"
_PROJECT_ROOT = Path(__file__).resolve().parents[2]
_PR_SET_PDEATHSIG = 1


class ServerError(Tumor3DError):
    """The Prefect server could not be started, reached or stopped (an environment error)."""


@dataclass(frozen=True)
class ServerInfo:
    """A running server: its process, where it listens, where it logs."""

    pid: int
    port: int
    api_url: str
    log: str = ""
    started_utc: str = ""
    #: The warm command runner beside it (:mod:`tumor3d.flows.daemon`), 0 if none.
    runner_pid: int = 0


@dataclass(frozen=True)
class ServerStatus:
    """What ``tumor3d server status`` reports.

    ``state`` is ``"running"`` (process alive and healthy), ``"unhealthy"``
    (process alive, API not answering), ``"stale"`` (state file names a dead
    process) or ``"stopped"`` (no state file).
    """

    state: str
    state_file: str
    info: ServerInfo | None = None

    @property
    def line(self) -> str:
        """One line for a user."""
        if self.info is None:
            return f"no tumor3d Prefect server running (state file {self.state_file} absent)"
        i = self.info
        where = f"pid {i.pid}, {i.api_url}, log {i.log}"
        if i.runner_pid:
            from tumor3d.flows.daemon import DAEMON_MODULE

            alive = _pid_is_our_server(i.runner_pid, DAEMON_MODULE)
            where += f"; runner pid {i.runner_pid} ({'up' if alive else 'gone'})"
        return {
            "running": f"running and healthy: {where}",
            "unhealthy": f"process alive but the API does not answer /health: {where}",
            "stale": f"stale state file {self.state_file}: process {i.pid} is gone",
        }[self.state]


def state_dir() -> Path:
    """The state folder: ``$TUMOR3D_HOME`` or ``~/.tumor3d``."""
    env = os.environ.get(STATE_ENV)
    return Path(env).expanduser() if env else Path.home() / ".tumor3d"


def _state_file() -> Path:
    return state_dir() / "server.json"


def _read_state() -> ServerInfo | None:
    try:
        data = json.loads(_state_file().read_text())
        return ServerInfo(**{k: data[k] for k in ServerInfo.__dataclass_fields__ if k in data})
    except (OSError, ValueError, TypeError, KeyError):
        return None


def _write_state(info: ServerInfo) -> None:
    path = _state_file()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(asdict(info), indent=2) + "\n")
    os.replace(tmp, path)


def _pid_is_our_server(pid: int, module: str = SERVER_MODULE) -> bool:
    """The process exists and (where /proc can tell) runs ``module`` (this server's)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return False  # someone else's process took the pid
    cmdline = Path(f"/proc/{pid}/cmdline")
    if cmdline.exists():
        try:
            args = cmdline.read_bytes().split(b"\0")
        except OSError:
            return True
        if not args or not args[0]:  # a zombie
            return False
        return module.encode() in args
    return True


def healthy(api_url: str, timeout_s: float = 2.0) -> bool:
    """True if ``<api_url>/health`` answers 200."""
    try:
        with urllib.request.urlopen(f"{api_url.rstrip('/')}/health", timeout=timeout_s) as r:
            return r.status == 200
    except (OSError, urllib.error.URLError, ValueError):
        return False


def server_status() -> ServerStatus:
    """Whether the background server is running, and where."""
    info = _read_state()
    where = str(_state_file())
    if info is None:
        return ServerStatus("stopped", where)
    if not _pid_is_our_server(info.pid):
        return ServerStatus("stale", where, info)
    return ServerStatus("running" if healthy(info.api_url) else "unhealthy", where, info)


def _free_port() -> int:
    with contextlib.closing(socket.socket(socket.AF_INET, socket.SOCK_STREAM)) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _spawn(
    port: int,
    *,
    parent: int | None,
    ephemeral: bool,
    log: Path | None,
    new_session: bool | None = None,
) -> subprocess.Popen:
    """The server process (``new_session``: default, only without ``parent``)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(_PROJECT_ROOT), *([env["PYTHONPATH"]] if env.get("PYTHONPATH") else [])]
    )
    env.pop("PREFECT_API_URL", None)  # the server must not talk to another server
    args = [sys.executable, "-m", SERVER_MODULE, "--port", str(port)]
    if parent is not None:
        args += ["--parent", str(parent)]
    if ephemeral:
        args.append("--ephemeral")
    out = open(log, "ab") if log is not None else subprocess.DEVNULL  # noqa: SIM115
    try:
        return subprocess.Popen(
            args,
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=out,
            stderr=subprocess.STDOUT,
            # the background server leaves the terminal's session (no SIGINT from ^C)
            start_new_session=parent is None if new_session is None else new_session,
            cwd=str(_PROJECT_ROOT),
        )
    finally:
        if log is not None:
            out.close()


def _spawn_runner(log: Path) -> int:
    """Start the warm command runner (:mod:`tumor3d.flows.daemon`) in the background; its pid.

    Same environment as the server's command (so a later command in it is
    served), own session, output appended to ``log``.
    """
    from tumor3d.flows.daemon import DAEMON_MODULE

    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(_PROJECT_ROOT), *([env["PYTHONPATH"]] if env.get("PYTHONPATH") else [])]
    )
    with open(log, "ab") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", DAEMON_MODULE],
            env=env, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT,
            start_new_session=True, cwd=str(_PROJECT_ROOT),
        )  # fmt: skip
    return proc.pid


def _stop_runner(pid: int) -> None:
    from tumor3d.flows.daemon import DAEMON_MODULE, socket_path

    if pid > 0 and _pid_is_our_server(pid, DAEMON_MODULE):
        with contextlib.suppress(ProcessLookupError, PermissionError):
            os.kill(pid, signal.SIGTERM)
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and _pid_is_our_server(pid, DAEMON_MODULE):
            with contextlib.suppress(ChildProcessError):
                if os.waitpid(pid, os.WNOHANG)[0] == pid:
                    break
            time.sleep(0.05)
    socket_path().unlink(missing_ok=True)


def _wait_healthy(proc: subprocess.Popen, api_url: str, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if proc.poll() is not None:
            raise ServerError(f"the Prefect server exited with code {proc.returncode} at start-up")
        if healthy(api_url, timeout_s=1.0):
            return
        time.sleep(0.2)
    _terminate(proc.pid)
    raise ServerError(
        f"the Prefect server did not answer {api_url}/health within {timeout_s:.0f} s "
        "(PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS raises the limit)"
    )


def _startup_timeout_s() -> float:
    try:
        return float(os.environ.get("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "120"))
    except ValueError:
        return 120.0


def _terminate(pid: int, grace_s: float = 10.0) -> None:
    """SIGTERM, then SIGKILL after ``grace_s``; reaps the process if it is our child."""
    try:
        os.kill(pid, signal.SIGTERM)
    except ProcessLookupError:
        return
    deadline = time.monotonic() + grace_s
    while time.monotonic() < deadline:
        with contextlib.suppress(ChildProcessError):
            if os.waitpid(pid, os.WNOHANG)[0] == pid:
                return
        if not _pid_is_our_server(pid):
            return
        time.sleep(0.1)
    with contextlib.suppress(ProcessLookupError):
        os.kill(pid, signal.SIGKILL)
    with contextlib.suppress(ChildProcessError):
        os.waitpid(pid, 0)


def start_server(
    port: int | None = None, timeout_s: float | None = None
) -> tuple[ServerInfo, bool]:
    """Start the background server (or find the one running): ``(info, started_now)``.

    A stale state file is replaced. Raises :class:`ServerError` when the
    server does not become healthy in time (the process is then stopped).
    """
    status = server_status()
    if status.state == "running" and status.info is not None:
        return status.info, False
    if status.state == "unhealthy" and status.info is not None:
        _stop_runner(status.info.runner_pid)
        _terminate(status.info.pid)
    elif status.state == "stale" and status.info is not None:
        _stop_runner(status.info.runner_pid)
    folder = state_dir()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ServerError(f"{folder}: cannot create the state folder ({exc.strerror})") from None
    log = folder / "server.log"
    port = port or _free_port()
    api_url = f"http://127.0.0.1:{port}/api"
    proc = _spawn(port, parent=None, ephemeral=False, log=log)
    info = ServerInfo(
        pid=proc.pid, port=port, api_url=api_url, log=str(log),
        started_utc=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    )  # fmt: skip
    _write_state(info)
    try:
        _wait_healthy(proc, api_url, timeout_s or _startup_timeout_s())
    except ServerError:
        _state_file().unlink(missing_ok=True)
        raise
    if not os.environ.get("TUMOR3D_NO_DAEMON"):  # the warm runner of run/demo
        info = ServerInfo(**{**asdict(info), "runner_pid": _spawn_runner(folder / "runner.log")})
        _write_state(info)
    return info, True


def stop_server() -> ServerStatus:
    """Stop the background server and remove its state file; returns the status before."""
    status = server_status()
    if status.info is not None:
        _stop_runner(status.info.runner_pid)
    if status.info is not None and status.state in ("running", "unhealthy"):
        _terminate(status.info.pid)
    _state_file().unlink(missing_ok=True)
    return status


# ---------------------------------------------------------------- use in a command


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
    if url and not healthy(url, timeout_s=timeout_s):
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
        status = server_status()
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
    temporary server (:func:`_spawn`: ephemeral, no telemetry, ``--parent``): it stops
    itself when its process dies, even by ``kill -9`` (Prefect's outlived a killed
    kernel). It is spawned from a thread of its own that lives as long as the process:
    ``PR_SET_PDEATHSIG`` fires when the *thread* that spawned the child exits, so a
    call made from a short-lived thread would otherwise take the server down after
    it. Its own session: a Ctrl-C in a script's terminal interrupts the script, not
    the server. A server found dead (its process ended) is started again.

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
        port = _free_port()
        api_url = f"http://127.0.0.1:{port}/api"
        proc = _spawn_from_a_lasting_thread(port)
        try:
            _wait_healthy(proc, api_url, _startup_timeout_s())
        except BaseException:
            _terminate(proc.pid, grace_s=5.0)
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
            _terminate(proc.pid, grace_s=5.0)
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
    """:func:`_spawn` a Python call's server from the one spawner thread, which never ends."""
    import queue

    with _SPAWNER_LOCK:
        thread = _SPAWNER.get("thread")
        if thread is None or not thread.is_alive():
            requests: queue.Queue = queue.Queue()

            def spawner() -> None:
                while True:
                    at, reply = requests.get()
                    try:
                        reply.put(_spawn(
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
            _terminate(got.pid, grace_s=5.0)


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
    status = server_status()
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
    port = _free_port()
    api_url = f"http://127.0.0.1:{port}/api"
    proc = _spawn(port, parent=os.getpid(), ephemeral=not services, log=None)
    try:
        _wait_healthy(proc, api_url, _startup_timeout_s())
        with _use_api(api_url, drain=True), _watch_server(api_url, server=proc), _this_process():
            yield api_url
    finally:
        if proc.poll() is None:  # (the watch may have reaped it: its pid is then free)
            _terminate(proc.pid, grace_s=5.0)


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


#: Exit code of a server process stopped by SIGINT (a Ctrl-C in its command's terminal).
EXIT_CTRL_C = 130

#: Called with the exit code just before a command ends because its server went away
#: (the warm runner's copy reports the code to its client).
EXIT_HOOKS: list[Callable[[int], None]] = []


_LAST_LINE_LOCK = threading.Lock()


def last_line(text: str, *, quiet_stdout: bool = False) -> None:
    """Write a command's last line to stderr and drop whatever is written there after it.

    Called as a command ends early (Ctrl-C, SIGTERM, a vanished server), before
    ``os._exit``: this process's other threads (Prefect's event and log services, whose
    server has just gone) may still write to stderr, and logging off is not enough, since
    a record made before it can be written after (a test run saw the events worker's
    "failed to process item" after the Ctrl-C line). Here stderr's file descriptor is
    pointed at the null device first, then the line is written to the stderr it was.
    ``quiet_stdout``: stdout too (a terminal's live progress bar, redrawn by its own
    thread until the exit, would move up over the line and erase it). Child processes
    that share the descriptor (a local Dask cluster's workers) are not silenced. Once
    per process: a second caller (the server watch beside a Ctrl-C) writes nothing.
    """
    import logging

    if not _LAST_LINE_LOCK.acquire(blocking=False):
        return  # another caller is writing the line; it ends the process
    logging.disable(logging.CRITICAL)
    try:
        encoding = codecs.lookup(getattr(sys.stderr, "encoding", None) or "utf-8").name
    except (LookupError, TypeError):
        encoding = "utf-8"
    data = (text + "\n").encode(encoding, "backslashreplace")
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            stream.flush()  # what was written before the line stays before it
    try:
        original = os.dup(2)
        null = os.open(os.devnull, os.O_WRONLY)
        if quiet_stdout:
            with contextlib.suppress(OSError):
                os.dup2(null, 1)
        os.dup2(null, 2)
        os.close(null)
    except OSError:  # no stderr descriptor to redirect: the line as any other
        with contextlib.suppress(Exception):
            sys.stderr.write(text + "\n")
            sys.stderr.flush()
        return
    with contextlib.suppress(OSError):
        os.write(original, data)


#: Seconds between two looks at the server's port, and refusals in a row that end the command.
_WATCH_PERIOD_S, _WATCH_REFUSALS = 1.0, 3
#: Seconds the watch leaves a command whose temporary server a Ctrl-C stopped to its own
#: Ctrl-C handler (a SIGINT sent to that server alone would otherwise leave the command
#: retrying a dead server).
_WATCH_CTRL_C_GRACE_S = 20.0


def _refused(api_url: str) -> bool:
    """True only if nothing listens on the API's port (a slow server is not refused)."""
    from urllib.parse import urlsplit

    parts = urlsplit(api_url)
    port = parts.port or (443 if parts.scheme == "https" else 80)
    try:
        with socket.create_connection((parts.hostname or "127.0.0.1", port), timeout=5.0):
            return False
    except ConnectionRefusedError:
        return True
    except OSError:  # a timeout, an unreachable network for a moment: not proof
        return False


@contextlib.contextmanager
def _watch_server(api_url: str, server: subprocess.Popen | None = None) -> Iterator[None]:
    """End the command (one line, exit 3) if the server stops listening while the body runs.

    Prefect's clients retry a vanished server for minutes, printing each
    retry, then fail with tracebacks. Nothing is left half-published: a
    patient folder is swapped in whole or not at all, and a re-run continues
    from the cache.

    ``server`` is the command's own temporary server process, if it has one. It
    shares the terminal's process group, so a Ctrl-C stops it too: a server that
    exited for SIGINT (:data:`EXIT_CTRL_C`) leaves the ending to the command's own
    Ctrl-C handling (one line, exit 130), which a busy main thread may run seconds
    later, for :data:`_WATCH_CTRL_C_GRACE_S`; one that is still shutting down is given
    a few more periods.
    """
    stop = threading.Event()

    def watch() -> None:
        refusals = 0
        while not stop.wait(_WATCH_PERIOD_S):
            refusals = refusals + 1 if _refused(api_url) else 0
            if refusals >= _WATCH_REFUSALS and server is not None:
                code = server.poll()
                if code in (EXIT_CTRL_C, -signal.SIGINT) and refusals * _WATCH_PERIOD_S < (
                    _WATCH_CTRL_C_GRACE_S
                ):
                    continue  # a Ctrl-C: the command's own handler ends it (exit 130)
                if code is None and refusals < 4 * _WATCH_REFUSALS:
                    continue  # not listening any more, still exiting: look again
            if refusals >= _WATCH_REFUSALS and not stop.is_set():
                with contextlib.suppress(Exception):
                    last_line(  # a terminal's progress bar would erase it (last_line)
                        f"error: the Prefect server {api_url} stopped answering during the "
                        "command (results published before it are complete; a re-run "
                        "continues from the cache)",
                        quiet_stdout=sys.stdout.isatty(),
                    )
                for hook in EXIT_HOOKS:
                    with contextlib.suppress(Exception):
                        hook(3)
                os._exit(3)

    thread = threading.Thread(target=watch, name="tumor3d-server-watch", daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()


# ---------------------------------------------------------------- the server process


def _watch_parent(parent: int) -> None:
    """Stop this process when ``parent`` dies (it is then re-parented)."""
    if sys.platform.startswith("linux"):
        with contextlib.suppress(Exception):
            import ctypes

            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    if os.getppid() != parent:  # the parent died before prctl took effect
        os._exit(0)

    def watchdog() -> None:
        while os.getppid() == parent:
            time.sleep(0.5)
        os.kill(os.getpid(), signal.SIGTERM)  # uvicorn's graceful shutdown
        time.sleep(10.0)
        os._exit(0)

    threading.Thread(target=watchdog, name="tumor3d-parent-watchdog", daemon=True).start()


def _serve(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog=f"python -m {SERVER_MODULE}")
    parser.add_argument("--port", type=int, required=True)
    parser.add_argument("--parent", type=int, default=None, help="stop when this pid dies")
    parser.add_argument("--ephemeral", action="store_true", help="no UI, no services")
    args = parser.parse_args(argv)
    if args.parent is not None:
        _watch_parent(args.parent)
    os.environ["PREFECT__SERVER_FINAL"] = "1"
    if args.ephemeral:
        os.environ["PREFECT__SERVER_EPHEMERAL"] = "1"
        os.environ["PREFECT_UI_ENABLED"] = "0"
    os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")
    _run_uvicorn("prefect.server.api.server:create_app", args.port, factory=True, lifespan="on")


def _run_uvicorn(app: Any, port: int, **options: Any) -> None:
    """Serve ``app`` on ``127.0.0.1:port`` with uvicorn until a signal stops it.

    uvicorn shuts down gracefully on SIGINT or SIGTERM, then raises the signal again
    with the previous handlers back: for SIGINT (a Ctrl-C in the command's terminal)
    the process exits :data:`EXIT_CTRL_C`, so that the command's watch
    (:func:`_watch_server`) tells a Ctrl-C from a crash.
    """
    signal.signal(signal.SIGINT, lambda signum, frame: sys.exit(EXIT_CTRL_C))
    import uvicorn

    uvicorn.run(app, host="127.0.0.1", port=port, log_level="error", **options)


if __name__ == "__main__":  # pragma: no cover - the server process
    _serve()
