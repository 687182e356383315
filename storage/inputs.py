"""Content digests of user inputs, for the ingest stage's cache key."""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

from tumor3d.errors import InputError, os_error_path, os_error_text

__all__ = [
    "detached_data_files",
    "input_digest",
    "input_files",
    "input_location",
    "input_signature",
]

_SIDECAR_SUFFIXES = (".json", ".yaml", ".yml")
_CHUNK = 1 << 20
_DETACHED_HEADERS = (".nhdr", ".mhd")
#: Formats whose header may name another file holding the voxels.
_HEADER_FORMATS = (".nhdr", ".mhd", ".nrrd", ".mha")
_HEADER_PROBE = 1 << 16
# NRRD "data file: x.raw" / "datafile: x.raw"; MetaImage "ElementDataFile = x.raw"
_DATA_FILE_LINE = re.compile(
    r"^(?:data ?file\s*:|ElementDataFile\s*=)\s*(.+?)\s*$", re.IGNORECASE | re.MULTILINE
)


def _stem(path: Path) -> str:
    name = path.name
    for ext in (".nii.gz", ".nii"):
        if name.endswith(ext):
            return name[: -len(ext)]
    return path.stem


def _header_text(header: Path) -> str:
    """The header part of a NRRD/MetaImage file (latin-1), at most 64 KiB."""
    with open(header, "rb") as fh:
        text = fh.read(_HEADER_PROBE).decode("latin-1")
    if header.name.lower().endswith((".nrrd", ".nhdr")):
        text = text.split("\n\n", 1)[0]  # a NRRD header ends at its first blank line
    return text


def _named_files(text: str, match: re.Match[str]) -> list[str]:
    """The file names a data-file line gives: one, a pattern's, or a LIST's."""
    ref = match.group(1)
    if ref.upper() == "LIST" or ref.upper().startswith("LIST "):
        return [ln.strip() for ln in text[match.end() :].splitlines() if ln.strip()]
    if "%" in ref:  # a printf pattern and its index range: "slice%03d.raw 1 40 1"
        return [ref.split()[0]]
    return [ref]


def _check_inside(header: Path, name: str) -> None:
    """Refuse a data file named outside the header's folder (absolute, or up through ``..``)."""
    folder = os.path.normpath(os.path.abspath(header.parent))
    target = os.path.normpath(os.path.join(folder, name))
    if os.path.isabs(name) or os.path.commonpath([folder, target]) != folder:
        raise InputError(
            f"its header names the data file {name!r} outside the header's folder; a "
            "detached header's data must lie in its folder (or below it)",
            path=str(header),
        )


def detached_data_files(header: str | Path) -> list[Path]:
    """The voxel-data files a NRRD/MetaImage header points to (resolved).

    A single named file is returned when it exists; for a list, a file-name
    pattern or anything not understood, every other regular file in the
    header's folder (over-inclusion only costs a cache miss, or refuses an
    output folder holding one of them).

    Raises
    ------
    InputError
        If the header names a data file outside its own folder (an absolute
        path or ``../``): one line naming the header.
    """
    header = Path(header)
    if not header.name.lower().endswith(_HEADER_FORMATS):
        return []
    try:
        text = _header_text(header)
    except OSError:
        return []
    match = _DATA_FILE_LINE.search(text)
    if match is None:
        return []
    ref = match.group(1)
    if ref.upper() == "LOCAL":
        return []  # the data follow the header in the same file
    for name in _named_files(text, match):
        _check_inside(header, name)
    if " " not in ref and "%" not in ref and ref.upper() != "LIST":
        target = (header.parent / ref).resolve()
        if target.is_file():
            return [target]
    if not header.name.lower().endswith(_DETACHED_HEADERS):
        return []
    return sorted(f.resolve() for f in header.parent.iterdir() if f.is_file() and f != header)


def input_files(path: str | Path) -> list[Path]:
    """Every file an input consists of, resolved: what publishing must never replace.

    The input itself; for a detached header its data file(s)
    (:func:`detached_data_files`) and any sidecar of the same stem; for a
    folder, the folder and the targets of the symbolic links in it.

    Raises
    ------
    InputError
        A header naming a data file outside its folder.
    """
    p = Path(path).expanduser()
    found = [p.resolve()]
    if p.is_dir():
        found += [f.resolve() for f in p.rglob("*") if f.is_symlink()]
    elif p.is_file():
        found += detached_data_files(p)
        stem = _stem(p)
        found += [p.with_name(stem + s).resolve() for s in _SIDECAR_SUFFIXES
                  if p.with_name(stem + s).is_file()]  # fmt: skip
    return found


def _hash_file(h: hashlib._Hash, path: Path, label: str) -> None:
    h.update(label.encode() + b"\0")
    with open(path, "rb") as fh:
        while chunk := fh.read(_CHUNK):
            h.update(chunk)
    h.update(b"\0")


def input_location(path: str | Path) -> str:
    """SHA-256 of the input's resolved absolute path: where it is, not what it holds.

    Recorded in ``provenance.json`` (``input.location_sha256``) so that a re-run
    of the same file is told from another file of the same name without
    writing the path itself (folder names may hold a patient's name) into the
    outputs.

    >>> a, b = "/data/pat3/flair.nii.gz", "/data/pat3/../pat3/flair.nii.gz"
    >>> input_location(a) == input_location(b) != input_location("/data/pat4/flair.nii.gz")
    True
    """
    resolved = os.path.abspath(os.path.realpath(os.fspath(path)))
    return hashlib.sha256(resolved.encode("utf-8", "surrogateescape")).hexdigest()


def input_digest(path: str | Path) -> str:
    """SHA-256 over everything a reader may read for this input.

    For a file: its bytes plus those of any sidecar beside it with the same
    stem (``x.nii.gz`` -> ``x.json``), and for a detached NRRD/MetaImage
    header (``.nhdr``, ``.mhd``) the bytes of the data file(s) it names.
    For a folder (DICOM series, image stack): the relative names and bytes
    of all its regular files, in sorted order. Locations do not enter the
    digest, so moving an input keeps it.

    Raises
    ------
    InputError
        If the path does not exist or cannot be read (one line naming it).
    """
    p = Path(path)
    if not p.exists():
        raise InputError("no such file or folder", path=str(p))
    try:
        return _input_digest(p)
    except OSError as exc:
        raise InputError(
            f"cannot read the input ({os_error_text(exc)})", os_error_path(exc, p)
        ) from None


def _input_digest(p: Path) -> str:
    h = hashlib.sha256(b"tumor3d-input-v1\0")
    if p.is_dir():
        files = sorted(f for f in p.rglob("*") if f.is_file())
        for f in files:
            _hash_file(h, f, f.relative_to(p).as_posix())
    else:
        _hash_file(h, p, "image")
        if p.name.lower().endswith(_HEADER_FORMATS):
            for data_file in detached_data_files(p):
                _hash_file(h, data_file, "data:" + data_file.name)
        stem = _stem(p)
        for suffix in _SIDECAR_SUFFIXES:
            side = p.with_name(stem + suffix)
            if side.is_file():
                _hash_file(h, side, "sidecar" + suffix)
    return h.hexdigest()


def input_signature(path: str | Path) -> tuple[tuple[str, int, int, int, int], ...] | None:
    """What the file system says of every file :func:`input_digest` reads, without reading it.

    Name, size, modification and change times (ns) and inode of the input,
    its sidecars and detached data files (a folder: every regular file in
    it), in order: equal signatures mean the content was not rewritten in
    between (as far as the file system's timestamps tell). ``None`` if a file
    cannot be examined.
    """
    p = Path(path)
    try:
        if p.is_dir():
            files = sorted(f for f in p.rglob("*") if f.is_file())
        else:
            stem = _stem(p)
            files = [p, *detached_data_files(p)]
            files += [p.with_name(stem + s) for s in _SIDECAR_SUFFIXES
                      if p.with_name(stem + s).is_file()]  # fmt: skip
        stats = [(os.fspath(f), f.stat()) for f in files]
    except (OSError, InputError):
        return None
    return tuple(
        (name, st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino) for name, st in stats
    )
