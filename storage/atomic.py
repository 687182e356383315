"""Files written whole, and what a killed writer leaves behind.

A file is written under a temporary name in its destination folder, flushed,
fsynced and renamed over its final name (:func:`atomic_write_bytes`), so a
crash never leaves a half-written file under that name. The temporary name,
``.<name>.tmp-<host tag>-<pid>-<random>`` (:data:`TMP_NAME`), says which
process of which machine wrote it, so that one left by a killed writer can be
told from one being written (:func:`writer_gone`) and removed
(:func:`remove_stale_tmp`, which the artifact store's sweep runs) while a live
writer's is never touched. :func:`check_writable_dir` names an unwritable
output folder before any work starts.

The artifact store (:mod:`tumor3d.storage.store`) writes its objects through
here, as do the publisher, the records and the reports.
"""

from __future__ import annotations

import errno
import hashlib
import os
import re
import socket
import tempfile
import uuid
from collections.abc import Iterable
from pathlib import Path

__all__ = [
    "HOST_TAG",
    "STALE_TMP_S",
    "TMP_NAME",
    "atomic_write_bytes",
    "check_writable_dir",
    "process_alive",
    "remove_stale_tmp",
    "writer_gone",
]


def _host_identity() -> str:
    """Who can ask this process's pids: the host name, this boot and the pid namespace.

    Two machines of one name differ by their boot, two containers of one name by
    their pid namespace; Linux's ``/proc`` gives those two, elsewhere the host name
    alone.
    """
    parts = [socket.gethostname()]
    try:
        parts.append(Path("/proc/sys/kernel/random/boot_id").read_text().strip())
        parts.append(str(os.stat("/proc/self/ns/pid").st_ino))
    except OSError:
        pass
    return "\0".join(parts)


#: This machine and pid namespace, in temporary file names: 8 hex digits of
#: :func:`_host_identity`'s SHA-256. A writer of the same tag can be asked by pid.
HOST_TAG = hashlib.sha256(_host_identity().encode()).hexdigest()[:8]

#: A temporary file or upload whose writer cannot be asked (another machine's, an
#: object store's) untouched for this long is a killed writer's (seconds; a write
#: takes seconds).
STALE_TMP_S = 3600.0

#: ``.<name>.tmp-<host tag>-<pid>-<random>``, the temporary name of
#: :func:`atomic_write_bytes` (``.<name>.tmp-<pid>-<random>`` before the host tag).
TMP_NAME = re.compile(r"^\.(?P<name>.+)\.tmp-(?:(?P<host>[0-9a-f]{8})-)?(?P<pid>\d+)-[0-9a-f]{8}$")


def process_alive(pid: int) -> bool:
    """True if process ``pid`` of this machine exists (ours, or another user's)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def writer_gone(
    host: str | None, pid: int, path: Path, *, now: float, max_age_s: float = STALE_TMP_S
) -> bool:
    """Whether a temporary file or folder, named with its writer's host tag and pid, is left.

    Left by a writer that is gone: this machine's and pid namespace's
    (:data:`HOST_TAG`) when its process no longer exists; any when ``path`` is
    untouched for ``max_age_s`` (another machine's, whose pids cannot be asked
    here, or one whose pid was since reused). Raises ``OSError`` when ``path``
    cannot be examined (the caller leaves it).
    """
    if host == HOST_TAG and not process_alive(pid):
        return True
    return now - Path(path).stat().st_mtime > max_age_s


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename.

    The temporary file lives in the destination folder (same file system),
    is fsynced, then atomically renamed over ``path``. Its name,
    ``.<name>.tmp-<host tag>-<pid>-<random>``, says which process wrote it,
    so that one left by a killed process can be told from one being written
    (:func:`remove_stale_tmp`).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{HOST_TAG}-{os.getpid()}-{uuid.uuid4().hex[:8]}")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except OSError as exc:
        if exc.errno is None or exc.filename is not None:
            raise
        # a write's or fsync's error names no file (a full disk: "no space left on device"
        # alone, a user audit): the file it was for
        raise OSError(exc.errno, exc.strerror, str(path)) from exc
    finally:
        if tmp.exists():
            tmp.unlink()


def remove_stale_tmp(found: Iterable[Path], *, now: float, max_age_s: float) -> list[str]:
    """Remove those of ``found`` that are temporary files of writers that are gone.

    A file is removed when its name is one of :func:`atomic_write_bytes`
    (:data:`TMP_NAME`) and :func:`writer_gone` says its writer is gone; any
    other file, a live writer's, and one that cannot be examined or removed
    (renamed into place meanwhile, another user's, read-only) is left as it is.

    Parameters
    ----------
    found : iterable of Path
        Candidate files (a glob of ``.*.tmp-*`` names).
    now : float
        The time to judge their age by (seconds since the epoch).
    max_age_s : float
        Age after which a file whose writer cannot be asked counts as left.

    Returns
    -------
    list of str
        The files removed.
    """
    removed: list[str] = []
    for tmp in found:
        m = TMP_NAME.match(tmp.name)
        if m is None:
            continue
        try:
            stale = writer_gone(m["host"], int(m["pid"]), tmp, now=now, max_age_s=max_age_s)
            if stale:
                tmp.unlink()
        except OSError:  # renamed into place meanwhile, another user's, read-only
            continue
        if stale:
            removed.append(str(tmp))
    return removed


def check_writable_dir(folder: Path, *, create: bool = True) -> None:
    """Check that a file can be created in ``folder``, made with its parents if ``create``.

    Called before any work by the commands and flows that write results there, so
    an immutable or read-only output folder is named at once instead of after every
    stage has run. Without ``create`` (a check before the input is validated: a
    refused command leaves nothing behind) an absent folder is judged by its
    nearest existing parent, where it would be made.

    Raises
    ------
    OSError
        Naming ``folder`` (not the probe's random name): it cannot be made or written.
    """
    folder = Path(folder)
    where = folder
    if not create:
        while not where.exists() and where.parent != where:
            where = where.parent
        if where.exists() and not where.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(where))
    try:
        if create:
            folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".tumor3d-probe-", dir=where)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror, str(folder)) from None
    os.close(fd)
    os.unlink(probe)
