"""Publishing a result folder as one unit: staging folder, fsync, rename swap.

``<out_dir>/<name>/`` is replaced as a whole: files are written to a hidden
staging folder ``<out_dir>/.<name>.partial-<host>-<pid>-<random>`` beside it
(``<host>``: :data:`tumor3d.storage.store.HOST_TAG`), fsynced, and the staging
folder is renamed into place (the previous folder, if any, is first renamed
aside to ``.<name>.old-<host>-<pid>-<random>`` and removed
afterwards; restored if the swap fails). A failed run leaves nothing under
the final name.

Four safety rules:

* :func:`check_output_not_input` -- a folder that is, or contains, an input
  (any file it consists of: a detached header's data file, a sidecar,
  :func:`tumor3d.storage.inputs.input_files`) is never removed or replaced (the
  caller checks before any work; a cohort checks every row's folder against
  every row's inputs, :func:`check_outputs_not_inputs`);
* :func:`check_replaceable` -- only a tumor3d result folder (or an empty
  one) is ever replaced: a folder of the user's own files that happens to
  have the patient's name is refused (the caller checks before any work,
  and :func:`staged_folder` checks again at entry and right before the swap);
  a local folder only: an ``s3://`` output (``tumor3d.storage.remote_publish``)
  replaces every object under its prefix;
* :func:`check_same_input` -- for a patient id derived from the file name,
  a folder holding another input file's results is not replaced (checked
  before any work and, by :func:`staged_folder`, right before the swap);
* :func:`clean_stale_staging` -- staging and trash folders left by a killed
  run are removed by the next publish into the folder, whatever their name:
  this machine's when their process is gone, another machine's (a folder
  shared over the network) when untouched for an hour; those of a live
  concurrent run are left alone.

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
import time
import uuid
from collections.abc import Callable, Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

from tumor3d.errors import InputError
from tumor3d.storage.atomic import HOST_TAG, STALE_TMP_S, process_alive, writer_gone
from tumor3d.storage.inputs import input_files

__all__ = [
    "PUBLISH_MANIFEST",
    "RESULT_MARKERS",
    "check_destination",
    "check_output_not_input",
    "check_outputs_not_inputs",
    "check_replaceable",
    "check_same_input",
    "clean_stale_staging",
    "is_tumor3d_result",
    "published_is_current",
    "staged_folder",
    "write_publish_manifest",
]

#: The hidden file of a published folder that records its key and file digests.
PUBLISH_MANIFEST = ".tumor3d-publish-key.json"

_MANIFEST_FORMAT = 1

#: Files that mark a folder as a tumor3d result (one published before the publish
#: manifest existed still holds ``provenance.json``): only such a folder is replaced,
#: and only when the file's content is tumor3d's (:func:`is_tumor3d_result`: other
#: pipelines write a ``provenance.json`` too).
RESULT_MARKERS = (PUBLISH_MANIFEST, "provenance.json")


def _json_object(path: Path) -> dict | None:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def is_tumor3d_result(folder: str | Path) -> bool:
    """Whether ``folder`` holds a tumor3d result: its publish manifest, or its provenance.

    The manifest (:data:`PUBLISH_MANIFEST`) with its ``key`` and ``files``, or a
    ``provenance.json`` whose ``versions`` name ``tumor3d``: the file names alone
    are not enough (another pipeline's ``provenance.json`` is someone's result).
    """
    folder = Path(folder)
    manifest = _json_object(folder / PUBLISH_MANIFEST)
    if manifest is not None and {"key", "files"} <= manifest.keys():
        return True
    prov = _json_object(folder / "provenance.json")
    return prov is not None and isinstance(prov.get("versions"), dict) and (
        "tumor3d" in prov["versions"]
    )


#: ``.<name>.partial-<host>-<pid>-<random>`` and ``.old-`` (without ``<host>-``
#: before it was added: such a folder's writer is asked by pid, for its own name only).
_LEFTOVER = re.compile(
    r"^\.(?P<name>.+)\.(?:partial|old)-(?:(?P<host>[0-9a-f]{8})-)?(?P<pid>\d+)-[0-9a-f]{8}$"
)


def _over_input(target: Path, src: Path) -> InputError:
    return InputError(
        f"the output folder {target} is or contains the input {src}; publishing "
        "replaces that folder as a whole and would delete the input: choose another "
        "--out or patient id",
        path=str(src),
    )


def check_output_not_input(final: str | Path, inputs: Iterable[str | Path]) -> None:
    """Refuse to publish into ``final`` when it is, or contains, one of ``inputs``.

    Publishing replaces ``final`` as a whole, so an input inside it would be
    deleted. Every file an input consists of counts
    (:func:`tumor3d.storage.inputs.input_files`: a ``.mhd`` header's data file too).

    Raises
    ------
    InputError
        Naming the input and the output folder (or a header naming a data
        file outside its folder).
    """
    check_outputs_not_inputs([final], inputs)


def check_outputs_not_inputs(finals: Iterable[str | Path], inputs: Iterable[str | Path]) -> None:
    """:func:`check_output_not_input` for many folders and inputs at once.

    A cohort: no row's folder may be or contain any row's input (a brain mask
    kept in another patient's published folder would be replaced when that
    patient is published). Linear in the number of folders and input files.
    """
    holders: dict[Path, Path] = {}
    for item in inputs:
        for src in input_files(item):
            for folder in (src, *src.parents):
                holders.setdefault(folder, src)
    for final in finals:
        target = Path(final).expanduser().resolve()
        if target in holders:
            raise _over_input(target, holders[target])


def check_replaceable(final: str | Path) -> None:
    """Refuse to publish into ``final`` unless it is absent, empty or a tumor3d result.

    Publishing replaces ``final`` as a whole. A folder that is not a tumor3d
    result (:func:`is_tumor3d_result`: no tumor3d content in the files of
    :data:`RESULT_MARKERS`) is someone's own files under the patient's name
    (``--out ~/project --patient-id data``), which would be deleted; a file
    or a symbolic link there would be moved aside.

    Raises
    ------
    InputError
        Naming the folder and what to do.

    Examples
    --------
    >>> import tempfile
    >>> out = Path(tempfile.mkdtemp())
    >>> check_replaceable(out / "p1")  # absent: fine
    >>> (out / "p1").mkdir(); _ = (out / "p1" / "notes.txt").write_text("mine")
    >>> check_replaceable(out / "p1")
    Traceback (most recent call last):
    ...
    tumor3d.errors.InputError: ...p1: this folder exists and is not a tumor3d result ...
    """
    target = Path(final).expanduser()
    if not (target.exists() or target.is_symlink()):
        return
    if target.is_symlink():
        raise InputError(
            "this output path is a symbolic link; publishing would replace the link (not "
            "what it points to): choose another --out or patient id",
            path=str(target),
        )
    if not target.is_dir():
        raise InputError(
            "this output path exists and is not a folder; publishing would replace it: "
            "choose another --out or patient id",
            path=str(target),
        )
    if is_tumor3d_result(target) or not any(target.iterdir()):
        return
    raise InputError(
        "this folder exists and is not a tumor3d result (no tumor3d "
        f"{' or '.join(RESULT_MARKERS)} in it); publishing replaces the folder as a whole and "
        "would delete its files: choose another --out or patient id, or remove the folder "
        "yourself",
        path=str(target),
    )


def check_same_input(
    final: str | Path,
    digest: str | Callable[[], str],
    *,
    location: str | None = None,
    suggestion: str | None = None,
) -> None:
    """Refuse to publish into ``final`` when it holds the results of another input.

    For a patient id derived from the file name (no ``--patient-id``): two
    inputs of the same name (``pat3/flair.nii.gz``, ``pat4/flair.nii.gz``)
    get the same id, and the second would silently replace the first. The
    record in ``final/provenance.json`` (``input``) is the same input when its
    ``location_sha256`` is ``location`` (:func:`tumor3d.storage.inputs.input_location`:
    the same file, edited or not; a header fixed as a note asked is a re-run)
    or its ``digest_sha256`` is ``digest`` (:func:`tumor3d.storage.inputs.input_digest`:
    the same content, moved). ``digest`` may be a callable, called only when the
    location does not decide (the content is hashed only then). A folder
    without a readable record is left to :func:`check_replaceable`.

    Raises
    ------
    InputError
        Naming the folder, the other input and, with ``suggestion``, an id to give.
    """
    doc = _json_object(Path(final).expanduser() / "provenance.json")
    old = None if doc is None else doc.get("input")
    if not isinstance(old, dict) or "digest_sha256" not in old:
        return
    if location is not None and old.get("location_sha256") == location:
        return
    old_digest, old_name = str(old["digest_sha256"]), str(old.get("name", "?"))
    if old_digest == (digest() if callable(digest) else digest):
        return
    hint = f" (e.g. --patient-id {suggestion})" if suggestion else ""
    raise InputError(
        f"this folder holds the results of another input file ({old_name}, SHA-256 "
        f"{old_digest[:12]}...) under the same patient id, which was derived from the file "
        f"name: give --patient-id{hint} to keep both, or --patient-id "
        f"{Path(final).name} to replace it",
        path=str(Path(final).expanduser()),
    )


def check_destination(
    final: str | Path,
    inputs: Iterable[str | Path],
    *,
    derived_from: str | Callable[[], str] | None = None,
    location: str | None = None,
    suggestion: str | None = None,
) -> None:
    """The destination rules of a patient's folder ``final``, checked before any work.

    :func:`check_output_not_input` (never over an input), :func:`check_replaceable`
    (only a tumor3d result or an empty folder is replaced) and, with
    ``derived_from`` (the input's digest, or a callable giving it, when the
    patient id was derived from its file name), :func:`check_same_input`.
    """
    check_output_not_input(final, inputs)
    check_replaceable(final)
    if derived_from is not None:
        check_same_input(final, derived_from, location=location, suggestion=suggestion)


def clean_stale_staging(
    out_dir: str | Path, name: str, *, max_age_s: float = STALE_TMP_S
) -> list[Path]:
    """Remove the staging and trash folders of killed publishers in ``out_dir``.

    Whatever patient it was for, a folder whose writer is gone by the store's rule
    for its temporary files (:func:`tumor3d.storage.store.writer_gone`): this
    machine's when its process is gone, any (another machine's, on a folder shared
    over a network file system) when untouched for ``max_age_s``; one named before
    the host tag was added, when it is ``name``'s and its pid is gone. A live publisher's
    folder is never touched. Housekeeping: a folder that cannot be examined or
    removed is left.

    Returns
    -------
    list of Path
        The folders removed.
    """
    folder = Path(out_dir)
    removed: list[Path] = []
    if not folder.is_dir():
        return removed
    now = time.time()
    for entry in folder.iterdir():
        m = _LEFTOVER.match(entry.name)
        if m is None:
            continue
        try:
            if not entry.is_dir():
                continue
            if m["host"] is None:
                stale = m["name"] == name and not process_alive(int(m["pid"]))
            else:  # as the store's temporary files
                stale = writer_gone(m["host"], int(m["pid"]), entry, now=now, max_age_s=max_age_s)
        except OSError:
            continue
        if stale:
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
    return f"{HOST_TAG}-{os.getpid()}-{uuid.uuid4().hex[:8]}"


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
def staged_folder(
    out_dir: str | Path, name: str, *, check: Callable[[Path], None] | None = None
) -> Iterator[Path]:
    """Yield an empty staging folder; on normal exit it replaces ``<out_dir>/<name>``.

    ``<out_dir>/<name>`` must be absent, empty or a tumor3d result
    (:func:`check_replaceable`), and pass ``check`` (e.g. :func:`check_same_input`),
    both at entry and again right before the swap: a concurrent run may have put
    its folder there meanwhile. Leftovers of killed runs
    (:func:`clean_stale_staging`) are cleaned first. On an exception
    the staging folder is removed and ``<out_dir>/<name>`` is untouched; an
    OS error that names no file (a full disk while writing) is re-raised
    naming ``<out_dir>/<name>``.

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

    def checks() -> None:
        check_replaceable(final)
        if check is not None:
            check(final)

    checks()
    staging = out / f".{name}.partial-{_tag()}"
    staging.mkdir()
    try:
        yield staging
        _fsync_tree(staging)
        checks()
        _swap_into_place(staging, final)
    except OSError as exc:
        shutil.rmtree(staging, ignore_errors=True)
        if exc.filename is None and exc.errno is not None:
            # a write's ENOSPC/EIO names no file: name the folder being published
            raise OSError(exc.errno, exc.strerror or str(exc), str(final)) from exc
        raise
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
