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
import lzma
import zipfile
import zlib

import numpy as np

from tumor3d.errors import InputError, exception_line

__all__ = ["MAX_ARRAY_BYTES", "UNREADABLE", "archive_error", "check_archive"]

#: The most a model's arrays may take once unpacked (the shipped ones: 0.3-0.6 MB).
MAX_ARRAY_BYTES = 256 * 2**20

#: What reading a damaged or hostile archive with numpy raises (MemoryError: an array too
#: large to hold; TypeError: a structured array cast to numbers): the loaders turn each
#: into one line (:func:`archive_error`'s words).
UNREADABLE = (
    OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error, MemoryError,
    NotImplementedError, RuntimeError, lzma.LZMAError, TypeError,
)  # fmt: skip


def check_archive(data: bytes, *, source: str, limit: int | None = None) -> None:
    """Refuse an archive whose entries declare more than ``limit`` bytes unpacked.

    ``limit`` defaults to :data:`MAX_ARRAY_BYTES` (read at the call). Both sizes count:
    an entry's in the zip directory (reading never yields more: zipfile stops there) and
    the array its ``.npy`` header declares (numpy allocates it before reading). An
    archive or header that cannot be read is left to the loader, which names what it is.

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
    >>> import numpy as np
    >>> header = io.BytesIO()  # 128 bytes declaring 2**42 int64 values
    >>> np.lib.format.write_array_header_1_0(
    ...     header, {"descr": "<i8", "fortran_order": False, "shape": (2**42,)})
    >>> buf = io.BytesIO()
    >>> with zipfile.ZipFile(buf, "w") as zf:
    ...     zf.writestr("feature.npy", header.getvalue())
    >>> try:
    ...     check_archive(buf.getvalue(), source="m.npz")
    ... except InputError as exc:
    ...     print(str(exc)[:36])
    m.npz: its arrays take 33554432 MB u
    """
    try:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            infos = zf.infolist()
            total = sum(info.file_size for info in infos)
            declared = sum(_declared_bytes(zf, info) for info in infos)
    except (zipfile.BadZipFile, OSError, ValueError, EOFError):
        return
    limit = MAX_ARRAY_BYTES if limit is None else limit
    total = max(total, declared)
    if total == float("inf"):
        raise InputError(f"{source}: an array header declares a negative size")
    if total > limit:
        raise InputError(
            f"{source}: its arrays take {total / 2**20:.0f} MB unpacked, more than any "
            f"tumor3d model ({limit // 2**20} MB at most)"
        )


def _declared_bytes(zf: zipfile.ZipFile, info: zipfile.ZipInfo) -> float:
    """The bytes of the array an entry's ``.npy`` header declares (0 for another entry).

    Whatever the entry's name (numpy reads any entry that starts with the ``.npy`` magic);
    a negative dimension counts as infinitely many bytes.
    """
    try:
        with zf.open(info) as fh:
            if fh.read(len(np.lib.format.MAGIC_PREFIX)) != np.lib.format.MAGIC_PREFIX:
                return 0
            version = tuple(fh.read(2))
            read = np.lib.format.read_array_header_1_0
            if version != (1, 0):
                read = np.lib.format.read_array_header_2_0
            shape, _, dtype = read(fh)
    except Exception:  # noqa: BLE001  (hostile bytes: any failure is the loader's to name)
        return 0
    if any(int(d) < 0 for d in shape):
        return float("inf")
    return float(np.prod(shape, dtype=np.float64)) * dtype.itemsize


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
