"""Cached stage results as Prefect stores them: written and read only as plain JSON.

A store may be shared (a lab's network disk, an s3 bucket), so whoever can
write it must not be able to make the tool run or import code. Prefect lets
each result record name the serializer that decodes it
(``metadata.serializer``): a record saying ``{"type": "pickle"}`` would be
unpickled, and Prefect's JSON decoder imports whatever module a
``{"__class__": ...}`` object names. Here:

* :class:`StageOutputSerializer` (type :data:`SERIALIZER_TYPE`) is the only
  serializer of stage results: plain :func:`json.dumps` of a
  :class:`~tumor3d.tasks.spec.StageOutput` and plain :func:`json.loads` back, validated
  against the model (no type-directed decoding);
* :func:`screen_record` checks a record's raw bytes before Prefect decodes
  them: plain JSON, exactly this serializer, a valid sealed ``StageOutput``
  stored under the key it names (:attr:`StageOutput.key`); anything else is
  refused (:class:`UntrustedRecord`), which Prefect treats as a cache miss, so
  the stage is recomputed and its record rewritten (the store heals);
* :class:`ScreenedResultFolder` and :class:`ScreenedRemoteFolder` are the result
  storage blocks that screen every record they read, so the bytes Prefect
  decodes are the bytes that were screened (no window between a check and a
  read). Writes replace the record file (through a rename), never following a
  symlink planted in its place.
"""

from __future__ import annotations

import json
import logging
import os
import re
import stat
from pathlib import Path
from typing import ClassVar, Literal

from prefect.filesystems import LocalFileSystem, RemoteFileSystem
from prefect.serializers import Serializer
from pydantic import ValidationError

from tumor3d.storage.objectstore import put_is_atomic, read_object
from tumor3d.storage.store import atomic_write_bytes
from tumor3d.tasks.spec import StageOutput

__all__ = [
    "MAX_RECORD_BYTES",
    "SERIALIZER_TYPE",
    "ScreenedRemoteFolder",
    "ScreenedResultFolder",
    "StageOutputSerializer",
    "UntrustedRecord",
    "screen_record",
    "why_refused",
]

#: The ``metadata.serializer.type`` of every record this project writes.
SERIALIZER_TYPE = "tumor3d-stage-output"

#: A record's size limit: a stage output is a few kilobytes of references and values.
MAX_RECORD_BYTES = 1 << 20

#: A record's file name: a cache key (a hex digest), never a path.
_KEY = re.compile(r"^[0-9A-Za-z_-]{8,128}$")


class UntrustedRecord(ValueError):
    """A cached result record that must not be decoded (the stage is recomputed)."""


def _parse_output(blob: bytes | str) -> StageOutput:
    """A ``StageOutput`` from plain JSON, validated; :class:`UntrustedRecord` otherwise."""
    try:
        body = json.loads(blob)
    except (ValueError, UnicodeDecodeError) as exc:
        raise UntrustedRecord(f"its result is not JSON ({type(exc).__name__})") from None
    if not isinstance(body, dict):
        raise UntrustedRecord("its result is not a JSON object")
    try:
        return StageOutput.model_validate(body)
    except ValidationError as exc:
        raise UntrustedRecord(
            f"its result is not a stage output ({exc.error_count()} schema errors)"
        ) from None


class _NoRefusedExceptionRecords(logging.Filter):
    """Drop Prefect's warning that a failed task's exception could not be stored.

    Prefect tries to store the exception of a failed stage as its result, with the
    stage's serializer, which refuses anything but a stage output on purpose (no record
    of a random key in the store); its warning ("Failed to write result: ... serializer
    'tumor3d-stage-output'. You can try a different serializer") asked a user of the
    Python API to change a setting that is right. The failure itself is reported.
    """

    def filter(self, record: logging.LogRecord) -> bool:
        """False for that warning about this module's serializer."""
        return not (
            str(record.msg).startswith("Failed to write result")
            and SERIALIZER_TYPE in " ".join(str(a) for a in (record.args or ()))
        )


def _quiet_refused_exceptions() -> None:
    """Install :class:`_NoRefusedExceptionRecords` on Prefect's task-run logger, once."""
    runs = logging.getLogger("prefect.task_runs")
    if not any(isinstance(f, _NoRefusedExceptionRecords) for f in runs.filters):
        runs.addFilter(_NoRefusedExceptionRecords())


_quiet_refused_exceptions()  # wherever the serializer is: a command, a notebook, a Dask worker


class StageOutputSerializer(Serializer):  # type: ignore[type-arg]
    """Plain JSON of a :class:`~tumor3d.tasks.spec.StageOutput`; decoding imports nothing."""

    type: Literal["tumor3d-stage-output"] = SERIALIZER_TYPE  # type: ignore[assignment]

    def dumps(self, obj: StageOutput) -> bytes:
        """The output's fields as JSON (sorted keys)."""
        if not isinstance(obj, StageOutput):
            raise TypeError(f"only stage outputs are stored, not a {type(obj).__name__}")
        return json.dumps(obj.model_dump(mode="json"), sort_keys=True).encode()

    def loads(self, blob: bytes) -> StageOutput:
        """The output back, validated against the model."""
        return _parse_output(blob)


def screen_record(data: bytes, key: str) -> StageOutput:
    """The stage output of a raw Prefect result record stored under ``key``, if it is trusted.

    Parameters
    ----------
    data : bytes
        The record file's content.
    key : str
        The cache key it was read under (the record's file name).

    Returns
    -------
    StageOutput

    Raises
    ------
    UntrustedRecord
        If the record is not plain JSON, names another serializer than
        :data:`SERIALIZER_TYPE`, holds no valid sealed stage output, or holds
        one stored under another key (another patient's, another stage's).
    """
    try:
        record = json.loads(data)
    except (ValueError, UnicodeDecodeError) as exc:
        raise UntrustedRecord(f"not JSON ({type(exc).__name__}: {exc})") from None
    if not isinstance(record, dict) or not isinstance(record.get("metadata"), dict):
        raise UntrustedRecord("not a result record")
    serializer = record["metadata"].get("serializer")
    if serializer != {"type": SERIALIZER_TYPE}:
        named = serializer.get("type") if isinstance(serializer, dict) else serializer
        raise UntrustedRecord(f"it names the serializer {named!r}, not {SERIALIZER_TYPE!r}")
    result = record.get("result")
    if not isinstance(result, str):
        raise UntrustedRecord("its result is not a JSON text")
    out = _parse_output(result)
    if not out.verify():
        raise UntrustedRecord("its result failed its digest check (edited or corrupted)")
    if out.key != key:
        raise UntrustedRecord(
            f"it holds the {out.stage} result stored under another key "
            f"({out.key[:12] or 'none'}…, not {key[:12]}…)"
        )
    return out


def _record_name(path: str) -> str:
    name = Path(str(path)).name
    if not _KEY.match(name) or str(path) not in (name, f"./{name}"):
        raise UntrustedRecord(f"{path!r} is not a cache key")
    return name


class ScreenedResultFolder(LocalFileSystem):
    """A local ``prefect-results`` folder whose records are screened on every read."""

    _block_type_name: ClassVar[str] = "tumor3d screened result folder"
    _block_type_slug: ClassVar[str] = "tumor3d-screened-result-folder"

    def _record_path(self, path: str) -> Path:
        base = Path(self.basepath or ".").expanduser().resolve()
        return base / _record_name(path)

    def read_raw(self, path: str) -> bytes:
        """A record's bytes, unscreened; never through a symlink, never a FIFO or a huge file."""
        target = self._record_path(path)
        flags = os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0) | getattr(os, "O_NONBLOCK", 0)
        try:
            fd = os.open(target, flags)
        except OSError as exc:
            if target.is_symlink():
                raise UntrustedRecord("it is a symlink (records are plain files)") from None
            raise ValueError(f"Path {target} cannot be read ({exc.strerror}).") from None
        with os.fdopen(fd, "rb") as fh:
            if not stat.S_ISREG(os.fstat(fh.fileno()).st_mode):
                raise UntrustedRecord("it is not a regular file")
            data = fh.read(MAX_RECORD_BYTES + 1)
        if len(data) > MAX_RECORD_BYTES:
            raise UntrustedRecord(f"it is larger than {MAX_RECORD_BYTES:,} bytes")
        return data

    def read_path(self, path: str, _sync: bool | None = None) -> bytes:  # type: ignore[override]
        """The record stored under ``path`` (a cache key) if :func:`screen_record` trusts it."""
        data = self.read_raw(path)
        screen_record(data, _record_name(path))
        return data

    async def aread_path(self, path: str) -> bytes:  # type: ignore[override]
        """As :meth:`read_path`."""
        return self.read_path(path)

    def write_path(self, path: str, content: bytes, _sync: bool | None = None) -> str:  # type: ignore[override]
        """Write a record through a temporary file and a rename (a symlink is replaced)."""
        target = self._record_path(path)
        atomic_write_bytes(target, content)
        return str(target)

    async def awrite_path(self, path: str, content: bytes) -> str:  # type: ignore[override]
        """As :meth:`write_path`."""
        return self.write_path(path, content)


class ScreenedRemoteFolder(RemoteFileSystem):
    """An object store's ``prefect-results`` prefix whose records are screened on every read."""

    _block_type_name: ClassVar[str] = "tumor3d screened remote result folder"
    _block_type_slug: ClassVar[str] = "tumor3d-screened-remote-result-folder"

    def read_raw(self, path: str) -> bytes:
        """A record's bytes, unscreened (for diagnostics): one GET on S3."""
        return read_object(self.filesystem, self._resolve_path(_record_name(path)))

    def read_path(self, path: str, _sync: bool | None = None) -> bytes:  # type: ignore[override]
        """The record stored under ``path`` (a cache key) if :func:`screen_record` trusts it."""
        data = self.read_raw(path)
        screen_record(data, _record_name(path))
        return data

    async def aread_path(self, path: str) -> bytes:  # type: ignore[override]
        """As :meth:`read_path`."""
        return self.read_path(path)

    def write_path(self, path: str, content: bytes, _sync: bool | None = None) -> str:  # type: ignore[override]
        """Write a record: one PUT on S3, else as Prefect's ``RemoteFileSystem`` does.

        S3 has no folders to make, and its PUT is all-or-nothing.
        """
        fs = self.filesystem
        if not put_is_atomic(fs):
            return RemoteFileSystem.write_path(self, path, content, _sync=True)  # type: ignore[call-arg]
        key = self._resolve_path(path)
        fs.pipe_file(key, content)
        return key

    async def awrite_path(self, path: str, content: bytes) -> str:  # type: ignore[override]
        """As :meth:`write_path`."""
        return self.write_path(path, content)


def why_refused(data: bytes, key: str) -> str | None:
    """Why :func:`screen_record` refuses a record (None if it trusts it)."""
    try:
        screen_record(data, key)
    except UntrustedRecord as exc:
        return str(exc)
    return None
