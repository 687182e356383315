"""Model files as ``.npz`` archives of plain arrays: read within bounds, never unpickled.

The forests (:meth:`tumor3d.learned.forest.ForestModel.from_bytes`) and the U-Nets
(:func:`tumor3d.learned.cnn.unet_from_bytes`) are read from a user's files too
(``segment.learned_models``): :func:`check_archive` refuses, before anything is
unpacked, an archive whose arrays would take more memory than any model (a few
compressed kilobytes can declare gigabytes), and :func:`archive_error` says why an
archive could not be read without numpy's advice to load it unsafely.
"""

from __future__ import annotations

import io
import zipfile

from tumor3d.errors import InputError, exception_line

__all__ = ["MAX_ARRAY_BYTES", "archive_error", "check_archive"]

#: The most a model's arrays may take once unpacked (the shipped ones: 0.3-0.6 MB).
MAX_ARRAY_BYTES = 256 * 2**20


def check_archive(data: bytes, *, source: str, limit: int | None = None) -> None:
    """Refuse an archive whose entries declare more than ``limit`` bytes unpacked.

    ``limit`` defaults to :data:`MAX_ARRAY_BYTES` (read at the call).

    An archive zipfile cannot read is left to the loader, which names what it is.
    Reading an entry never yields more than its declared size (zipfile stops there).

    >>> import io, zipfile
    >>> buf = io.BytesIO()
    >>> with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
    ...     zf.writestr("a.npy", bytes(3 * 2**20))
    >>> len(buf.getvalue()) < 2**14
    True
    >>> try:
    ...     check_archive(buf.getvalue(), source="m.npz", limit=2**20)
    ... except InputError as exc:
    ...     print(exc)
    m.npz: its arrays take 3 MB unpacked, more than any tumor3d model (1 MB at most)
    """
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            total = sum(info.file_size for info in zf.infolist())
    except (zipfile.BadZipFile, OSError, ValueError, EOFError):
        return
    limit = MAX_ARRAY_BYTES if limit is None else limit
    if total > limit:
        raise InputError(
            f"{source}: its arrays take {total / 2**20:.0f} MB unpacked, more than any "
            f"tumor3d model ({limit // 2**20} MB at most)"
        )


def archive_error(exc: BaseException) -> str:
    """Why an ``.npz`` could not be read as a model, in words (never advice to unpickle).

    >>> archive_error(ValueError("Cannot load file containing pickled data ..."))
    'not an .npz archive of plain arrays (a model is never unpickled)'
    >>> archive_error(KeyError("feature is not a file in the archive"))
    'no array feature'
    """
    if "pickle" in str(exc):
        return "not an .npz archive of plain arrays (a model is never unpickled)"
    if isinstance(exc, KeyError):  # numpy: "feature is not a file in the archive"
        name = str(exc.args[0]).split(" is not a file")[0] if exc.args else ""
        return f"no array {name}".strip()
    return exception_line(exc)
