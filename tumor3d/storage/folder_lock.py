"""One writer per output folder: a command that finds another writing there stops at once.

Two commands publishing into the same ``--out`` (a cron job and a hand-started
re-run, or two triggers of a deployment) would each write their own patients
and cohort tables over the other's: the cohort table could then give one
run's volume for a patient whose folder holds the other run's. So every
command that writes a local output folder holds an exclusive lock on
``DIR/.tumor3d-writing`` (``fcntl.flock``) while it runs; a second one fails
at once with one line naming the folder and the command that holds it (its
pid, host and start time), an environment error (exit code 3).

The operating system releases the lock when its process ends, however it
ends (``kill -9`` included), so a stale lock cannot block a folder; the file
itself stays (hidden), rewritten by the next holder. Output folders on S3 are
not locked (no such lock there; ``README``, Artifact store on S3).
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import socket
from collections.abc import Iterator
from pathlib import Path

from tumor3d.storage.store import StoreError, utc_now

__all__ = ["LOCK_NAME", "FolderBusyError", "writing_folder"]

#: The lock file in an output folder.
LOCK_NAME = ".tumor3d-writing"


class FolderBusyError(StoreError):
    """Another command is writing the output folder."""


def _holder(fd: int) -> str:
    """Who holds the lock, from what it wrote in the file (best effort)."""
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        info = json.loads(os.read(fd, 4096).decode("utf-8"))
        return f"pid {info['pid']} on {info['host']}, since {info['started_utc']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "a process that did not say which"


@contextlib.contextmanager
def writing_folder(folder: str | os.PathLike[str]) -> Iterator[None]:
    """Hold ``folder``'s writer lock for the body (the folder is made if absent).

    Raises
    ------
    FolderBusyError
        Another process holds it: one line naming the folder and that process.
    OSError
        The folder or its lock file cannot be made (naming the folder).
    """
    path = Path(folder)
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd = os.open(path / LOCK_NAME, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror, str(path)) from None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            raise FolderBusyError(
                f"{path}: another tumor3d command is writing this folder ({_holder(fd)}); "
                "wait for it to end or give another output folder"
            ) from None
        record = {"pid": os.getpid(), "host": socket.gethostname(), "started_utc": utc_now()}
        with contextlib.suppress(OSError):  # who holds it is for the message only
            os.ftruncate(fd, 0)
            os.pwrite(fd, json.dumps(record).encode("utf-8"), 0)
        yield
    finally:
        os.close(fd)  # releases the lock
