"""Content digests of user inputs, for the ingest stage's cache key."""

from __future__ import annotations

import hashlib
from pathlib import Path

from tumor3d.errors import InputError

__all__ = ["input_digest"]

_SIDECAR_SUFFIXES = (".json", ".yaml", ".yml")
_CHUNK = 1 << 20


def _stem(path: Path) -> str:
    name = path.name
    for ext in (".nii.gz", ".nii"):
        if name.endswith(ext):
            return name[: -len(ext)]
    return path.stem


def _hash_file(h: hashlib._Hash, path: Path, label: str) -> None:
    h.update(label.encode() + b"\0")
    with open(path, "rb") as fh:
        while chunk := fh.read(_CHUNK):
            h.update(chunk)
    h.update(b"\0")


def input_digest(path: str | Path) -> str:
    """SHA-256 over everything a reader may read for this input.

    For a file: its bytes plus those of any sidecar beside it with the same
    stem (``x.nii.gz`` -> ``x.json``). For a folder (DICOM series, image
    stack): the relative names and bytes of all its regular files, in sorted
    order. Locations do not enter the digest, so moving an input keeps it.

    Raises
    ------
    InputError
        If the path does not exist.
    """
    p = Path(path)
    if not p.exists():
        raise InputError("no such file or folder", path=str(p))
    h = hashlib.sha256(b"tumor3d-input-v1\0")
    if p.is_dir():
        files = sorted(f for f in p.rglob("*") if f.is_file())
        for f in files:
            _hash_file(h, f, f.relative_to(p).as_posix())
    else:
        _hash_file(h, p, "image")
        stem = _stem(p)
        for suffix in _SIDECAR_SUFFIXES:
            side = p.with_name(stem + suffix)
            if side.is_file():
                _hash_file(h, side, "sidecar" + suffix)
    return h.hexdigest()
