"""One read of the input per run: the command line's check hands its scan to the ingest stage.

``tumor3d run`` reads the input before it starts Prefect, so that a bad
input fails in a second with one line (:func:`read_and_keep`); the ingest
stage then takes that scan (:func:`take_kept`) instead of reading the input
a second time. The scan is kept, one at a time per process, with the
options it was read with and the input's file-system signature
(:func:`tumor3d.storage.inputs.input_signature`: names, sizes, times and
inodes of every file the reader reads); it is handed over only for the same
options (the patient id aside: it names the scan, it does not change it)
while that signature is unchanged, else the stage reads as before. The
ingest stage's cache key is the input's content digest and the options,
as it was: where the scan comes from does not enter it.

In another process (a Dask worker) nothing is kept and the stage reads.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

from tumor3d.imaging.scan import Scan
from tumor3d.storage.inputs import input_signature
from tumor3d.storage.readers import read_scan
from tumor3d.storage.readers.nifti import nibabel_header_notes
from tumor3d.storage.readers.options import ReadOptions

__all__ = ["forget_kept", "kept_or_read", "read_and_keep", "read_noting", "take_kept"]

_LOCK = threading.Lock()
_KEPT: dict[str, tuple[tuple, tuple, Scan, list[str]]] = {}


def _where(path: str | os.PathLike[str]) -> str:
    return os.path.realpath(os.fspath(Path(path).expanduser()))


def read_noting(
    path: str | os.PathLike[str], options: ReadOptions, *, name: str | None = None
) -> tuple[Scan, list[str]]:
    """:func:`read_scan` with nibabel's header repairs as notes naming the file (``name``)."""
    with nibabel_header_notes(name or Path(path).name) as notes:
        scan = read_scan(path, options)
    return scan, notes


def read_and_keep(path: str | os.PathLike[str], options: ReadOptions) -> Scan:
    """Read the input (errors as :func:`read_scan`) and keep the scan for :func:`take_kept`.

    Replaces what was kept before. Nothing is kept when the input's
    signature cannot be taken, or changed during the read.
    """
    where = _where(path)
    before = input_signature(where)
    scan, notes = read_noting(path, options)
    with _LOCK:
        _KEPT.clear()
        if before is not None and input_signature(where) == before:
            _KEPT[where] = (before, options.content_key(), scan, notes)
    return scan


def take_kept(
    path: str | os.PathLike[str], options: ReadOptions, *, keep: bool = False
) -> tuple[Scan, list[str]] | None:
    """The kept scan of ``path`` and its header notes, if read with these options and unchanged.

    ``None`` otherwise (then read it). Taken, it is no longer kept, unless
    ``keep`` (a check before the ingest stage, such as a given brain mask's).
    """
    where = _where(path)
    with _LOCK:
        kept = _KEPT.get(where) if keep else _KEPT.pop(where, None)
    if kept is None:
        return None
    signature, key, scan, notes = kept
    if key != options.content_key() or input_signature(where) != signature:
        return None
    return scan, list(notes)


def kept_or_read(path: str | os.PathLike[str], options: ReadOptions) -> Scan:
    """The kept scan (still kept, for the ingest stage) or a fresh read: a check of a given mask."""
    kept = take_kept(path, options, keep=True)
    return kept[0] if kept is not None else read_scan(path, options)


def forget_kept() -> None:
    """Drop the kept scan (the end of a command)."""
    with _LOCK:
        _KEPT.clear()
