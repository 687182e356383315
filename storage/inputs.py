"""Content digests of user inputs, for the ingest stage's cache key."""

from __future__ import annotations

import hashlib
import os
import re
from pathlib import Path

from tumor3d.errors import InputError, os_error_path, os_error_text

__all__ = ["input_digest", "input_location"]

_SIDECAR_SUFFIXES = (".json", ".yaml", ".yml")
_CHUNK = 1 << 20
_DETACHED_HEADERS = (".nhdr", ".mhd")
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


def _detached_data_files(header: Path) -> list[Path]:
    """The voxel-data files a ``.nhdr``/``.mhd`` header points to.

    A single named file is returned when it exists; for a list, a file-name
    pattern or anything not understood, every other regular file in the
    header's folder (over-inclusion only costs a cache miss).
    """
    try:
        with open(header, "rb") as fh:
            text = fh.read(_HEADER_PROBE).decode("latin-1")
    except OSError:
        return []
    match = _DATA_FILE_LINE.search(text)
    if match is None:
        return []
    ref = match.group(1)
    if ref.upper() == "LOCAL":
        return []  # the data follow the header in the same file
    if " " not in ref and "%" not in ref and ref.upper() != "LIST":
        target = (header.parent / ref).resolve()
        if target.is_file():
            return [target]
    return sorted(f for f in header.parent.iterdir() if f.is_file() and f != header)


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
        if p.name.lower().endswith(_DETACHED_HEADERS):
            for data_file in _detached_data_files(p):
                _hash_file(h, data_file, "data:" + data_file.name)
        stem = _stem(p)
        for suffix in _SIDECAR_SUFFIXES:
            side = p.with_name(stem + suffix)
            if side.is_file():
                _hash_file(h, side, "sidecar" + suffix)
    return h.hexdigest()
