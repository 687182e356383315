"""The registry of input formats: which reader turns a file or folder into a `Scan`.

A *reader* is a function ``read(path, options) -> Scan`` (``options`` a
:class:`~tumor3d.storage.readers.options.ReadOptions` whose ``patient_id`` is
already set). A file reader is chosen by the file name's suffix; a folder
reader by ``claims(folder)`` (a stack's sidecar is there), or it is the
``fallback`` (DICOM) for a folder no other reader claims.

Adding a format = one function and one decorator, in a module listed in
:data:`READER_MODULES`::

    from tumor3d.storage.readers.registry import register_reader

    @register_reader("analyze", accepts="an Analyze file (.hdr, .img)", suffixes=(".hdr",))
    def _read_analyze(path, options):
        ...
        return scan_from_volume(...)

:func:`tumor3d.storage.readers.read_scan` dispatches through it, the error
for an unsupported file lists the registered formats, and ``tumor3d
methods`` prints them.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from tumor3d.errors import InputError
from tumor3d.imaging.scan import Scan
from tumor3d.storage.readers.options import ReadOptions

__all__ = [
    "READER_MODULES",
    "NotThisFormat",
    "Reader",
    "read_with_registry",
    "reader_for",
    "register_reader",
    "registered_readers",
]

#: Modules whose import registers readers, in the order the formats are listed.
READER_MODULES: tuple[str, ...] = (
    "tumor3d.storage.readers.nifti",
    "tumor3d.storage.readers.itk",
    "tumor3d.storage.readers.dicom",
    "tumor3d.storage.readers.stack",
)


class NotThisFormat(InputError):
    """Raised by a fallback reader: the folder holds nothing of its format."""


@dataclass(frozen=True)
class Reader:
    """A registered input format.

    Attributes
    ----------
    name : str
        Short name (``nifti``, ``dicom``, ...).
    accepts : str
        What to give, in words with its suffixes, as the error for an
        unsupported file lists it (``"a NIfTI file (.nii, .nii.gz)"``).
    read : callable
        ``read(path, options) -> Scan``.
    suffixes : tuple of str
        File readers: the lower-case name endings it reads.
    claims : callable or None
        Folder readers: ``claims(folder) -> bool``.
    fallback : bool
        The folder reader for a folder no other reader claims.
    slice_suffixes : tuple of str
        Folder readers: suffixes of one of its 2-D slices (a single one given
        as the input is refused as such).
    hint : callable or None
        Folder readers: ``hint(folder) -> InputError | None``, what to say when
        the fallback found nothing of its format in a folder (a stack
        without its sidecar).
    """

    name: str
    accepts: str
    read: Callable[[Path, ReadOptions], Scan]
    suffixes: tuple[str, ...] = ()
    claims: Callable[[Path], bool] | None = None
    fallback: bool = False
    slice_suffixes: tuple[str, ...] = ()
    hint: Callable[[Path], InputError | None] | None = None

    @property
    def is_folder(self) -> bool:
        """Whether it reads a folder (else a file)."""
        return self.claims is not None or self.fallback


_REGISTRY: dict[str, Reader] = {}


def register_reader(
    name: str,
    *,
    accepts: str,
    suffixes: tuple[str, ...] = (),
    claims: Callable[[Path], bool] | None = None,
    fallback: bool = False,
    slice_suffixes: tuple[str, ...] = (),
    hint: Callable[[Path], InputError | None] | None = None,
) -> Callable[[Callable[[Path, ReadOptions], Scan]], Callable[[Path, ReadOptions], Scan]]:
    """Decorator registering ``read(path, options) -> Scan`` as the reader ``name``.

    Give ``suffixes`` for a file format, ``claims`` or ``fallback=True`` for
    a folder format (see :class:`Reader`).

    Raises
    ------
    InputError
        A name taken by another function, a reader that is neither a file
        nor a folder reader, a suffix another reader already reads, or a
        second fallback.
    """
    is_folder = claims is not None or fallback
    if bool(suffixes) == is_folder:
        raise InputError(f"reader {name!r}: give suffixes (a file) or claims/fallback (a folder)")
    lower = tuple(s.lower() for s in suffixes)

    def deco(fn: Callable[[Path, ReadOptions], Scan]) -> Callable[[Path, ReadOptions], Scan]:
        old = _REGISTRY.get(name)
        if old is not None and old.read.__qualname__ != fn.__qualname__:
            raise InputError(f"a reader named {name!r} is already registered")
        for other in _REGISTRY.values():
            if other.name == name:
                continue
            if set(other.suffixes) & set(lower):
                raise InputError(f"reader {name!r}: {other.name!r} already reads {lower}")
            if fallback and other.fallback:
                raise InputError(f"reader {name!r}: {other.name!r} is already the fallback")
        _REGISTRY[name] = Reader(
            name, accepts, fn, lower, claims, bool(fallback), tuple(slice_suffixes), hint
        )
        return fn

    return deco


def registered_readers() -> dict[str, Reader]:
    """Every reader, after importing :data:`READER_MODULES` (name -> Reader, in that order)."""
    for module in READER_MODULES:
        importlib.import_module(module)

    def place(reader: Reader) -> int:
        module = reader.read.__module__
        return READER_MODULES.index(module) if module in READER_MODULES else len(READER_MODULES)

    # in the order of READER_MODULES (the import order may differ), then as registered
    return {r.name: r for r in sorted(_REGISTRY.values(), key=place)}


def _listing(readers: list[Reader]) -> str:
    """``"a, b, or c"`` of the readers' ``accepts``, files first."""
    words = [r.accepts for r in readers if not r.is_folder] + [
        r.accepts for r in readers if r.fallback
    ] + [r.accepts for r in readers if r.is_folder and not r.fallback]  # fmt: skip
    return ", ".join(words[:-1]) + ", or " + words[-1] if len(words) > 1 else "".join(words)


def reader_for(p: Path) -> Reader:
    """The reader of the existing file or folder ``p``.

    Raises
    ------
    InputError
        A file no reader reads (the message lists the formats), a single
        2-D slice of a folder format, or a path neither a file nor a folder.
    """
    readers = list(registered_readers().values())
    if p.is_file():
        lower = p.name.lower()
        for reader in readers:
            if reader.suffixes and lower.endswith(reader.suffixes):
                return reader
        slices = tuple(s for r in readers for s in r.slice_suffixes)
        if slices and lower.endswith(slices):
            raise InputError(
                "a single 2-D image was given where a stack is needed: at least 2 slices "
                f"are needed (give {_listing([r for r in readers if r.is_folder])})",
                str(p),
            )
        raise InputError(
            f"unsupported file type {''.join(p.suffixes) or '(no extension)'!r}: give "
            + _listing(readers),
            str(p),
        )
    if not p.is_dir():
        raise InputError("neither a regular file nor a folder", str(p))
    for reader in readers:
        if reader.claims is not None and reader.claims(p):
            return reader
    fallback = next((r for r in readers if r.fallback), None)
    if fallback is None:
        raise InputError("no reader takes a folder: give a file", str(p))
    return fallback


def read_with_registry(p: Path, options: ReadOptions) -> Scan:
    """Read ``p`` with its reader; a fallback that found nothing asks the others for a hint."""
    reader = reader_for(p)
    try:
        return reader.read(p, options)
    except NotThisFormat as exc:
        readers = list(registered_readers().values())
        if reader.fallback:
            for other in readers:
                hint = other.hint(p) if other.hint is not None else None
                if hint is not None:
                    raise hint from None
        # a plain InputError (the reader's own class is an internal signal), naming what a
        # folder may hold
        folders = [r for r in readers if r.is_folder]
        raise InputError(
            f"{exc.problem}; a folder input is {_listing(folders)}", exc.path
        ) from None
