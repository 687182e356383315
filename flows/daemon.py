"""The warm command runner beside the background server: ``run`` and ``demo`` in ~1 s.

A ``tumor3d`` command spends most of a cached run importing Prefect, numpy,
scipy, numba and the stage modules and deriving the stages' code digests
(reports/benchmarks.md: 3-5 s of a 4.7 s cached run). ``tumor3d server
start`` therefore also starts this runner, ``python -m tumor3d.flows.daemon``: one
process that has imported all of it once, listens on a Unix socket in the
state folder (``$TUMOR3D_HOME/run.sock``, mode 0600, peers of another user
refused) and forks a copy of itself for each command (the pre-fork model of
gunicorn's ``--preload``). The copy takes the client's standard input,
output and error (passed over the socket, ``SCM_RIGHTS``), working folder and
environment, and runs the command exactly as the client would have in its
own process (same code, same output on the same terminal, same exit code);
Ctrl-C in the client is relayed to it.

The console script (:func:`main`) imports only the standard library (and
:mod:`tumor3d.package_layout`, which does too) and
forwards ``run`` and ``demo`` when a runner answers; otherwise, and for
every other command, it runs the command in-process as before. The runner
refuses (and the client then runs in-process, saying why once) when it runs
other code than the client's (a file of the project changed since it
started: :func:`code_fingerprint`), another Python, or another Prefect /
tumor3d environment (``PREFECT_*``, ``TUMOR3D_*``, ``NUMBA_*`` variables).
``TUMOR3D_NO_DAEMON=1`` keeps a command in-process. The parent process never
runs a command itself and starts no thread, so forking it is safe.
"""

from __future__ import annotations

import array
import json
import os
import signal
import socket
import struct
import sys
from pathlib import Path

from tumor3d.package_layout import PROJECT_ROOT, SOURCE_FOLDERS

__all__ = ["DAEMON_MODULE", "code_fingerprint", "forward", "main", "socket_path"]

DAEMON_MODULE = "tumor3d.flows.daemon"
#: Commands the runner serves (one patient; the others run in-process).
FORWARDED = frozenset({"run", "demo"})
#: Environment variables that must match between client and runner.
_ENV_PREFIXES = ("PREFECT_", "TUMOR3D_", "NUMBA_")
#: Set by the runner itself (or by tumor3d.flows.cli at import), not compared.
_ENV_OWN = frozenset(
    {"PREFECT_LOGGING_LEVEL", "PREFECT_SERVER_ANALYTICS_ENABLED", "TUMOR3D_DAEMON_CHILD"}
)
#: The folders of the project's code under _ROOT: tumor3d/ and the folders mapped into it.
_PACKAGES = tuple(str(folder) for folder in SOURCE_FOLDERS)
_ROOT = PROJECT_ROOT
_MAX_HELLO = 1 << 20


def socket_path() -> Path:
    """``$TUMOR3D_HOME/run.sock`` (default ``~/.tumor3d/run.sock``)."""
    env = os.environ.get("TUMOR3D_HOME")
    return (Path(env).expanduser() if env else Path.home() / ".tumor3d") / "run.sock"


def code_fingerprint(root: Path = _ROOT) -> str:
    """Paths, sizes and modification times of the project's files (a few ms).

    Every ``.py`` file and shipped model of the packages, and the
    site-packages folders (a package installed, upgraded or removed): any
    edit, install or checkout changes it, so a runner started before it is
    not used.
    """
    import hashlib

    h = hashlib.sha256()
    import sysconfig

    for where in {sysconfig.get_paths()["purelib"], sysconfig.get_paths()["platlib"]}:
        try:  # a package installed, upgraded or removed changes its folder's entries
            h.update(f"{where}\0{os.stat(where).st_mtime_ns}\n".encode())
        except OSError:
            pass
    for pkg in _PACKAGES:
        base = root / pkg
        if not base.is_dir():
            continue
        for dirpath, dirnames, filenames in os.walk(base):
            dirnames[:] = sorted(d for d in dirnames if d != "__pycache__")
            for name in sorted(filenames):
                if name.endswith((".py", ".npz", ".js")):
                    p = os.path.join(dirpath, name)
                    st = os.stat(p)
                    h.update(f"{p}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()


def _env_subset(env: dict[str, str]) -> dict[str, str]:
    return {k: v for k, v in env.items() if k.startswith(_ENV_PREFIXES) and k not in _ENV_OWN}


def _forwardable(argv: list[str]) -> bool:
    if not argv or argv[0] not in FORWARDED:
        return False
    if os.environ.get("TUMOR3D_NO_DAEMON") or os.environ.get("TUMOR3D_DAEMON_CHILD"):
        return False
    # -v changes Prefect's logging set at import; --help needs no server
    return not any(a in ("-v", "--verbose", "--help") for a in argv)


def _read_line(sock: socket.socket) -> dict | None:
    buf = b""
    while not buf.endswith(b"\n"):
        chunk = sock.recv(4096)
        if not chunk:
            return None
        buf += chunk
        if len(buf) > _MAX_HELLO:
            return None
    try:
        msg = json.loads(buf)
    except ValueError:
        return None
    return msg if isinstance(msg, dict) else None


def forward(argv: list[str]) -> int | None:
    """Run ``tumor3d argv`` in the warm runner; its exit code, or None to run in-process."""
    path = socket_path()
    if not _forwardable(argv) or not path.exists():
        return None
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    try:
        sock.settimeout(2.0)
        sock.connect(str(path))
        hello = {
            "argv": argv,
            "cwd": os.getcwd(),
            "env": dict(os.environ),
            "exe": sys.executable,
            "fingerprint": code_fingerprint(),
        }
        fds = [sys.stdin.fileno(), sys.stdout.fileno(), sys.stderr.fileno()]
        sys.stdout.flush()
        sys.stderr.flush()
        socket.send_fds(sock, [json.dumps(hello).encode() + b"\n"], fds)
        reply = _read_line(sock)
    except Exception:  # no runner, a closed stdin (cron), ...: run in this process
        sock.close()
        return None
    if reply is None or not reply.get("accepted"):
        sock.close()
        if reply is not None and reply.get("reason"):
            print(
                f"note: the background runner was not used ({reply['reason']}); "
                "running in this process (`tumor3d server stop` then `start` renews it)",
                file=sys.stderr,
            )
        return None
    child = int(reply.get("pid", 0))
    sock.settimeout(None)

    def relay(signum: int) -> None:  # the command handles it as in-process: one line, its code
        if child > 0:
            try:
                os.kill(child, signum)
            except OSError:
                pass

    # SIGTERM (timeout, systemd) too: the child runs in a session of its own, so it would
    # otherwise go on writing after its client died silently with 143
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: relay(signum))
    try:
        while True:
            try:
                done = _read_line(sock)
                break
            except KeyboardInterrupt:
                relay(signal.SIGINT)
    finally:
        signal.signal(signal.SIGTERM, previous)
    sock.close()
    if done is None or "exit" not in done:
        print("error: the background runner ended the command without a result", file=sys.stderr)
        return 3
    return int(done["exit"])


def main() -> None:  # pragma: no cover - console entry
    """The ``tumor3d`` console script: forward to the warm runner, else run in-process."""
    code = forward(sys.argv[1:])
    if code is not None:
        os._exit(code)
    from tumor3d.flows.cli import main as cli_main

    cli_main()


# ---------------------------------------------------------------- the runner


def _peer_uid(conn: socket.socket) -> int:
    creds = conn.getsockopt(socket.SOL_SOCKET, socket.SO_PEERCRED, struct.calcsize("3i"))
    return struct.unpack("3i", creds)[1]


def _receive(conn: socket.socket) -> tuple[dict | None, list[int]]:
    """The client's hello and its three file descriptors."""
    fds = array.array("i")
    buf = b""
    while not buf.endswith(b"\n") and len(buf) < _MAX_HELLO:
        msg, anc, _flags, _addr = conn.recvmsg(65536, socket.CMSG_LEN(3 * fds.itemsize))
        for level, kind, data in anc:
            if level == socket.SOL_SOCKET and kind == socket.SCM_RIGHTS:
                usable = len(data) - (len(data) % fds.itemsize)
                fds.frombytes(data[:usable])
        if not msg:
            break
        buf += msg
    try:
        hello = json.loads(buf)
    except ValueError:
        hello = None
    return (hello if isinstance(hello, dict) else None), list(fds)


def _send(conn: socket.socket, msg: dict) -> None:
    try:
        conn.sendall(json.dumps(msg).encode() + b"\n")
    except OSError:
        pass


def _refusal(hello: dict, fingerprint: str, env: dict[str, str]) -> str | None:
    if hello.get("exe") != sys.executable:
        return f"it runs {sys.executable}, this command {hello.get('exe')}"
    if hello.get("fingerprint") != fingerprint:
        return "the project's files changed since it started"
    theirs = _env_subset({str(k): str(v) for k, v in (hello.get("env") or {}).items()})
    if theirs != env:
        diff = sorted(set(theirs.items()) ^ set(env.items()))
        return f"another environment ({diff[0][0]})"
    if not isinstance(hello.get("argv"), list) or not _forwardable_argv(hello["argv"]):
        return "not a command it serves"
    return None


def _forwardable_argv(argv: list) -> bool:
    return bool(argv) and all(isinstance(a, str) for a in argv) and argv[0] in FORWARDED


def _child(conn: socket.socket, hello: dict, fds: list[int]) -> None:  # pragma: no cover
    """In the forked copy: become the client's command, report its exit code, exit."""
    code = 1
    try:
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.signal(signal.SIGTERM, signal.SIG_DFL)
        signal.signal(signal.SIGCHLD, signal.SIG_DFL)
        for target, fd in zip((0, 1, 2), fds, strict=True):
            os.dup2(fd, target)
            os.close(fd)
        os.setsid()  # not the runner's session: the command's own process group
        os.environ.clear()
        os.environ.update({str(k): str(v) for k, v in hello["env"].items()})
        os.environ["TUMOR3D_DAEMON_CHILD"] = "1"
        os.chdir(hello["cwd"])
        sys.argv = ["tumor3d", *hello["argv"]]
        _send(conn, {"accepted": True, "pid": os.getpid()})
        from tumor3d.flows.server_watch import EXIT_HOOKS

        EXIT_HOOKS.append(lambda c: _send(conn, {"exit": int(c)}))
        from rich.console import Console

        import tumor3d.flows.cli as cli

        cli.console = Console()  # the client's terminal: colours and width as in-process
        cli.err_console = Console(stderr=True)
        try:
            code = cli.run_command(hello["argv"], prog_name="tumor3d")
        except KeyboardInterrupt:
            print("interrupted", file=sys.stderr)
            code = 130
            cli.finish_process()
    except BaseException as exc:  # never a traceback on the client's terminal
        try:
            print(f"error: the background runner failed: {exc}".splitlines()[0], file=sys.stderr)
        except Exception:
            pass
        code = 3
    finally:
        _send(conn, {"exit": int(code)})
        os._exit(int(code))


def _warm() -> None:
    """Import what a command needs and derive the stages' code digests, once."""
    import tumor3d.flows.cli  # noqa: F401
    import tumor3d.flows.patient  # noqa: F401
    from tumor3d.tasks import stages

    for spec in stages.STAGES.values():
        _ = spec.code_digest


def serve(path: Path | None = None) -> None:  # pragma: no cover - exercised in a subprocess
    """Listen on ``path`` (default :func:`socket_path`) and fork a copy per command."""
    path = path or socket_path()
    path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
    _warm()
    fingerprint = code_fingerprint()
    env = _env_subset(dict(os.environ))
    path.unlink(missing_ok=True)
    server = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    old = os.umask(0o177)
    try:
        server.bind(str(path))
    finally:
        os.umask(old)
    server.listen(16)
    signal.signal(signal.SIGCHLD, signal.SIG_IGN)  # children reaped by the kernel
    signal.signal(signal.SIGTERM, lambda *_: (path.unlink(missing_ok=True), os._exit(0)))
    print(f"tumor3d runner: pid {os.getpid()}, socket {path}", flush=True)
    while True:
        try:
            conn, _ = server.accept()
        except InterruptedError:
            continue
        try:
            if _peer_uid(conn) != os.getuid():
                conn.close()
                continue
            conn.settimeout(5.0)
            hello, fds = _receive(conn)
            conn.settimeout(None)
            why = "a malformed request" if hello is None or len(fds) != 3 else None
            why = why or _refusal(hello, fingerprint, env)
            if why is not None:
                _send(conn, {"accepted": False, "reason": why})
                for fd in fds:
                    os.close(fd)
                conn.close()
                continue
            pid = os.fork()
            if pid == 0:
                server.close()
                _child(conn, hello, fds)
            for fd in fds:
                os.close(fd)
            conn.close()
            print(f"served {hello['argv'][0]} in pid {pid}", flush=True)
        except OSError as exc:
            print(f"request failed: {exc}", flush=True)
            conn.close()


if __name__ == "__main__":  # pragma: no cover
    serve()
