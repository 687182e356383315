"""The local Prefect server the commands talk to: a background one, or a temporary one.

This module starts, stops and reports the servers, and is the server process itself.
Which API a command or a Python call uses is :mod:`tumor3d.flows.api_use`; the watch
that ends a command whose server went away, :mod:`tumor3d.flows.server_watch`.

Which Prefect API a command uses (:func:`tumor3d.flows.api_use.prefect_api`), in order:

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
import contextlib
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
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from tumor3d.errors import Tumor3DError
from tumor3d.package_layout import PROJECT_ROOT

__all__ = [
    "EXIT_CTRL_C",
    "SERVER_MODULE",
    "STATE_ENV",
    "ServerError",
    "ServerInfo",
    "ServerStatus",
    "healthy",
    "server_status",
    "start_server",
    "state_dir",
    "stop_server",
]

#: Environment variable naming the state folder (default ``~/.tumor3d``).
STATE_ENV = "TUMOR3D_HOME"
#: The module run as the server process (``python -m tumor3d.flows.server``).
SERVER_MODULE = "tumor3d.flows.server"
_PROJECT_ROOT = PROJECT_ROOT  # the folder holding tumor3d/: the repository, or site-packages
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
            if Path(self.state_file).exists():  # not a server's record (a user audit: "absent")
                return (
                    f"no tumor3d Prefect server known (state file {self.state_file} "
                    "unreadable: not a server's record)"
                )
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
            # ended, or its id given to another process since (a user audit: a live process
            # of that id was called "gone")
            "stale": f"stale state file {self.state_file}: process {i.pid} is not its server",
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


def _child_env() -> dict[str, str]:
    """A child's environment: this process's, with the project first on ``PYTHONPATH``."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        [str(_PROJECT_ROOT), *([env["PYTHONPATH"]] if env.get("PYTHONPATH") else [])]
    )
    return env


def _spawn(
    port: int,
    *,
    parent: int | None,
    ephemeral: bool,
    log: Path | None,
    new_session: bool | None = None,
) -> subprocess.Popen:
    """The server process (``new_session``: default, only without ``parent``)."""
    env = _child_env()
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

    env = _child_env()
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


#: Exit code of a server process stopped by SIGINT (a Ctrl-C in its command's terminal).
EXIT_CTRL_C = 130


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
    (:func:`tumor3d.flows.server_watch._watch_server`) tells a Ctrl-C from a crash.
    """
    signal.signal(signal.SIGINT, lambda signum, frame: sys.exit(EXIT_CTRL_C))
    import uvicorn

    uvicorn.run(app, host="127.0.0.1", port=port, log_level="error", **options)


if __name__ == "__main__":  # pragma: no cover - the server process
    _serve()
