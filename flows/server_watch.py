"""The watch of a command's Prefect server, and a command's last line.

While a command runs, :func:`_watch_server` looks at its server's port once a second:
a server that stops listening (killed, stopped) ends the command with one line and
exit code 3 (:func:`last_line`, then ``os._exit``) instead of minutes of Prefect's
retries and tracebacks. The exit hooks (:data:`EXIT_HOOKS`) run first.
"""

from __future__ import annotations

import codecs
import contextlib
import os
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator

from tumor3d.flows.server import EXIT_CTRL_C

__all__ = ["EXIT_HOOKS", "last_line"]

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
