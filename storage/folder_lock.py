"""One writer per output folder: a command that finds another writing there stops at once.

Two commands publishing into the same ``--out`` (a cron job and a hand-started
re-run, or two triggers of a deployment) would each write their own patients
and cohort tables over the other's: the cohort table could then give one
run's volume for a patient whose folder holds the other run's. So every
command that writes a local output folder holds an exclusive lock on
``DIR/.tumor3d-writing`` (``fcntl.flock``) while it runs; a second one fails
at once with one line naming the folder and the command that holds it (its
pid, host and start time), an environment error (exit code 3). A ``run`` holds
that lock shared, so runs of different patients into one folder go together
while a cohort command waits for none of them, and its patient's lock
(``DIR/.tumor3d-writing-<folder>``, :func:`patient_lock_name`) exclusively: two
runs of one patient into one folder both said ``ok`` for a folder that held one
of them (a user audit); the second now stops.

The operating system releases the lock when its process ends, however it
ends (``kill -9`` included), so a stale lock cannot block a folder; the file
itself stays (hidden), rewritten by the next holder; made writable by the
users the umask lets (a group-shared folder), opened read-only when another
user's file is not (``flock`` locks it all the same), never through a symbolic
link. On a file system that cannot lock (NFS without its lock daemon) the
command runs unlocked, as before. Output folders on S3 are not locked (no such
lock there; ``README``, Artifact store on S3).
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import socket
import stat
from collections.abc import Iterator
from pathlib import Path

from tumor3d.storage.refs import StoreError, utc_now

__all__ = ["LOCK_NAME", "FolderBusyError", "patient_lock_name", "writing_folder"]

#: The lock file in an output folder.
LOCK_NAME = ".tumor3d-writing"


class FolderBusyError(StoreError):
    """Another command is writing the output folder."""


_PATIENT = f"{LOCK_NAME}-"


def patient_lock_name(folder_name: str) -> str:
    """The lock file of one patient's folder, beside it in the output folder.

    >>> patient_lock_name("p1")
    '.tumor3d-writing-p1'
    """
    return f"{_PATIENT}{folder_name}"


def _holder(fd: int) -> str:
    """Who holds the lock, from what it wrote in the file (best effort)."""
    try:
        os.lseek(fd, 0, os.SEEK_SET)
        info = json.loads(os.read(fd, 4096).decode("utf-8"))
        return f"pid {info['pid']} on {info['host']}, since {info['started_utc']}"
    except (OSError, ValueError, KeyError, TypeError):
        return "a process that did not say which"


#: ``flock`` errors of a file system that cannot lock (NFS without its lock daemon, some
#: network and FUSE file systems): the command then runs unlocked, as before the lock.
_NO_LOCKING = frozenset({errno.ENOLCK, errno.EOPNOTSUPP, errno.ENOSYS, errno.EINVAL})


def _open_lock(lock: Path) -> tuple[int, bool]:
    """The lock file's descriptor (never through a symbolic link) and whether it is writable.

    Made readable and writable by everyone the umask lets (a group-shared folder): another
    user's file is opened read-only, which ``flock`` locks as well.
    """
    flags = os.O_CREAT | os.O_NOFOLLOW | os.O_CLOEXEC
    try:
        fd, writable = os.open(lock, os.O_RDWR | flags, 0o666), True
    except PermissionError:
        fd, writable = os.open(lock, os.O_RDONLY | os.O_NOFOLLOW | os.O_CLOEXEC), False
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise OSError(errno.EEXIST, "exists and is not a regular file", str(lock))
    return fd, writable


@contextlib.contextmanager
def writing_folder(
    folder: str | os.PathLike[str], *, name: str = LOCK_NAME, shared: bool = False
) -> Iterator[None]:
    """Hold ``folder``'s writer lock for the body (the folder is made if absent).

    ``name``: the lock file in ``folder`` (:data:`LOCK_NAME`, the whole folder's; a
    patient's is :func:`patient_lock_name`). ``shared``: held beside other shared
    holders, but never with an exclusive one: a ``run`` holds the folder's lock shared
    (many patients of one ``--out`` at once) and its patient's exclusively, a cohort
    command the folder's exclusively.

    Raises
    ------
    FolderBusyError
        Another process holds it: one line naming the folder and that process.
    OSError
        The folder or its lock file cannot be made or opened (naming the lock file; a
        symbolic link there is refused, never followed).
    """
    path = Path(folder)
    lock = path / name
    try:
        path.mkdir(parents=True, exist_ok=True)
        fd, writable = _open_lock(lock)
    except OSError as exc:
        target = lock if path.is_dir() else path
        raise OSError(exc.errno, exc.strerror, str(target)) from None
    try:
        try:
            fcntl.flock(fd, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        except BlockingIOError:
            what = "this folder" if name == LOCK_NAME else f"{name.removeprefix(_PATIENT)} here"
            raise FolderBusyError(
                f"{path}: another tumor3d command is writing {what} ({_holder(fd)}); "
                "wait for it to end or give another output folder"
            ) from None
        except OSError as exc:
            if exc.errno not in _NO_LOCKING:
                raise OSError(exc.errno, exc.strerror, str(lock)) from None
            writable = False  # a file system that cannot lock: unlocked, as before
        if writable:  # who holds it, for the message of the next one (best effort)
            record = {"pid": os.getpid(), "host": socket.gethostname(), "started_utc": utc_now()}
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)
                os.pwrite(fd, json.dumps(record).encode("utf-8"), 0)
        yield
    finally:
        os.close(fd)  # releases the lock
