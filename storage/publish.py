"""Publishing a result folder as one unit: staging folder, fsync, rename swap.

``<out_dir>/<name>/`` is replaced as a whole: files are written to a hidden
staging folder ``<out_dir>/.<name>.partial-<pid>-<random>`` beside it,
fsynced, and the staging folder is renamed into place (the previous folder,
if any, is first renamed aside to ``.<name>.old-<pid>-<random>`` and removed
afterwards; restored if the swap fails). A failed run leaves nothing under
the final name.

Two safety rules:

* :func:`check_output_not_input` -- a folder that is, or contains, an input
  is never removed or replaced (the caller checks before any work);
* :func:`clean_stale_staging` -- staging and trash folders left by a killed
  run (its process is gone) are removed by the next publish of that name;
  those of a live concurrent run are left alone.

A re-run whose result is already published need not rewrite it:
:func:`write_publish_manifest` records, in the staging folder, a key (the
caller's digest of everything the folder is made from) and the SHA-256 of
every file; :func:`published_is_current` is true only when the published
folder holds that same key and exactly those files, each with its digest (a
file edited, deleted or added means "not current": publish again).
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import re
import shutil
import uuid
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from tumor3d.errors import InputError

__all__ = [
    "PUBLISH_MANIFEST",
    "check_output_not_input",
    "clean_stale_staging",
    "published_is_current",
    "staged_folder",
    "write_publish_manifest",
]

#: The hidden file of a published folder that records its key and file digests.
PUBLISH_MANIFEST = ".tumor3d-publish-key.json"

_MANIFEST_FORMAT = 1

_LEFTOVER = re.compile(r"^\.(?P<name>.+)\.(?:partial|old)-(?P<pid>\d+)-[0-9a-f]{8}$")


def check_output_not_input(final: str | Path, inputs: Iterable[str | Path]) -> None:
    """Refuse to publish into ``final`` when it is, or contains, one of ``inputs``.

    Publishing replaces ``final`` as a whole, so an input inside it would be
    deleted.

    Raises
    ------
    InputError
        Naming the input and the output folder.
    """
    target = Path(final).expanduser().resolve()
    for item in inputs:
        src = Path(item).expanduser().resolve()
        if src == target or target in src.parents:
            raise InputError(
                f"the output folder {target} is or contains the input {src}; publishing "
                "replaces that folder as a whole and would delete the input: choose another "
                "--out or patient id",
                path=str(src),
            )


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def clean_stale_staging(out_dir: str | Path, name: str) -> list[Path]:
    """Remove ``.<name>.partial-*`` / ``.<name>.old-*`` folders whose process is gone.

    Returns
    -------
    list of Path
        The folders removed.
    """
    folder = Path(out_dir)
    removed: list[Path] = []
    if not folder.is_dir():
        return removed
    for entry in folder.iterdir():
        m = _LEFTOVER.match(entry.name)
        if m is None or m["name"] != name or not entry.is_dir():
            continue
        if _pid_alive(int(m["pid"])):
            continue
        shutil.rmtree(entry, ignore_errors=True)
        removed.append(entry)
    return removed


def _fsync_tree(folder: Path) -> None:
    for f in folder.rglob("*"):
        if f.is_file():
            with open(f, "rb") as fh:
                os.fsync(fh.fileno())
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _tag() -> str:
    return f"{os.getpid()}-{uuid.uuid4().hex[:8]}"


def _swap_into_place(staging: Path, final: Path, *, attempts: int = 20) -> None:
    """Replace ``final`` by ``staging`` with renames; restore the old one on failure.

    A concurrent publisher of the same name may put its folder in place
    between our two renames: then we move that one aside and try again, so
    the last writer wins and no folder is ever half-written.
    """
    for attempt in range(attempts):
        trash = final.with_name(f".{final.name}.old-{_tag()}")
        try:
            os.replace(final, trash)
            had_old = True
        except FileNotFoundError:
            had_old = False
        try:
            os.replace(staging, final)
        except OSError as exc:
            if had_old:
                try:
                    os.replace(trash, final)
                except OSError:  # another run's folder is there now: ours is obsolete
                    shutil.rmtree(trash, ignore_errors=True)
            if exc.errno in (errno.ENOTEMPTY, errno.EEXIST) and attempt < attempts - 1:
                continue
            raise
        if had_old:
            shutil.rmtree(trash, ignore_errors=True)
        return


@contextmanager
def staged_folder(out_dir: str | Path, name: str) -> Iterator[Path]:
    """Yield an empty staging folder; on normal exit it replaces ``<out_dir>/<name>``.

    Leftovers of killed runs for ``name`` are cleaned first. On an exception
    the staging folder is removed and ``<out_dir>/<name>`` is untouched.

    Examples
    --------
    >>> import tempfile
    >>> out = Path(tempfile.mkdtemp())
    >>> with staged_folder(out, "p1") as tmp:
    ...     _ = (tmp / "a.txt").write_text("x")
    >>> sorted(p.name for p in out.iterdir()), (out / "p1" / "a.txt").read_text()
    (['p1'], 'x')
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    clean_stale_staging(out, name)
    final = out / name
    staging = out / f".{name}.partial-{_tag()}"
    staging.mkdir()
    try:
        yield staging
        _fsync_tree(staging)
        _swap_into_place(staging, final)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise


def _file_digests(folder: Path) -> dict[str, str]:
    """Relative POSIX path -> SHA-256 of every file under ``folder`` but the manifest."""
    out: dict[str, str] = {}
    for f in sorted(folder.rglob("*")):
        rel = f.relative_to(folder).as_posix()
        if rel == PUBLISH_MANIFEST or f.is_dir():
            continue
        if not f.is_file():  # a symlink to nowhere, a socket...: never "current"
            raise OSError(errno.EINVAL, "not a regular file", str(f))
        h = hashlib.sha256()
        with open(f, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
        out[rel] = h.hexdigest()
    return out


def write_publish_manifest(staging: str | Path, key: str) -> str:
    """Record ``key`` and every file's digest in ``staging`` (call last, before the swap).

    Returns the manifest's file name (:data:`PUBLISH_MANIFEST`).
    """
    folder = Path(staging)
    doc = {"format": _MANIFEST_FORMAT, "key": key, "files": _file_digests(folder)}
    (folder / PUBLISH_MANIFEST).write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n")
    return PUBLISH_MANIFEST


def published_is_current(folder: str | Path, key: str) -> bool:
    """True if ``folder`` was published with ``key`` and every file is as published.

    False (publish again) when the folder or its manifest is missing or
    unreadable, the key differs, or any file was changed, deleted or added
    since. Reads every file once (a few MB for a patient).

    Examples
    --------
    >>> import tempfile
    >>> out = Path(tempfile.mkdtemp())
    >>> with staged_folder(out, "p1") as tmp:
    ...     _ = (tmp / "a.txt").write_text("x")
    ...     _ = write_publish_manifest(tmp, "k1")
    >>> published_is_current(out / "p1", "k1"), published_is_current(out / "p1", "k2")
    (True, False)
    >>> _ = (out / "p1" / "a.txt").write_text("y")
    >>> published_is_current(out / "p1", "k1")
    False
    """
    path = Path(folder)
    try:
        doc = json.loads((path / PUBLISH_MANIFEST).read_text())
        if not isinstance(doc, dict) or doc.get("format") != _MANIFEST_FORMAT:
            return False
        if doc.get("key") != key or not isinstance(doc.get("files"), dict):
            return False
        return _file_digests(path) == doc["files"]
    except (OSError, ValueError):
        return False
