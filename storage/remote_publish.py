"""Publishing result folders to an object store (``--out s3://bucket/prefix``).

The object-store counterpart of :mod:`tumor3d.storage.publish` (which it does not
replace: a patient's folder is still written and fsynced in a local
:func:`~tumor3d.storage.publish.staged_folder` first, then handed to
:func:`publish_folder`). An object store has no rename and no folders, so a
"folder" ``<url>/<name>/`` counts as published only when its **marker**
``<url>/<name>/.tumor3d-published.json`` is there and valid; the marker lists
every file with its size and SHA-256 and is written last:

1. every file is uploaded under a temporary prefix
   ``<url>/.tumor3d-tmp/<name>.<pid>-<random>/``;
2. the previous marker, if any, is removed (from here on a reader sees the
   folder as not published);
3. each file is copied (server side) to its final key and **read back**: its
   SHA-256 must be the staged file's, else :class:`~tumor3d.storage.store.StoreError`
   and no marker;
4. keys under ``<url>/<name>/`` that are not in the new file list (a previous
   version's) are removed, as the local swap replaces the folder as a whole;
5. the marker is written, then the temporary prefix removed.

A run killed anywhere before step 5 leaves no valid marker, so the folder is
not published (:func:`published_names` skips it, :func:`read_marker` returns
None) and the next publish of that name completes it. A folder whose marker
already lists exactly the staged files' digests, and whose objects still
match them (read back), is left alone, and so is one whose marker records the
same publish key when every stage was a cache hit and whose objects are still the
ones published (re-runs from the cache upload nothing, although files holding run
times differ). Whether they are is told by the listing that checks the sizes: the
marker records each object's ETag as the store gave it after the copy, and an object
written since (even with other bytes of the same size) has another; where the store
or an older marker gives no ETag, the objects are read back against their digests.
:func:`verify_folder` re-reads every listed file against its digest (a corrupted
or missing object is named).

Inputs are never touched: inputs are local files, and only keys under the
output prefix are written or removed.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
import uuid
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from tumor3d.storage.atomic import STALE_TMP_S
from tumor3d.storage.objectstore import (
    check_reachable,
    copy_object,
    first_line,
    modified_time,
    open_fs,
    read_object,
)
from tumor3d.storage.refs import StoreError, utc_now

__all__ = [
    "MARKER",
    "RemoteFolder",
    "published_names",
    "publish_files",
    "publish_folder",
    "read_marker",
    "verify_folder",
]

#: The completion marker of a published folder (written last).
MARKER = ".tumor3d-published.json"
#: The marker's format tag.
MARKER_FORMAT = "tumor3d-published/1"
#: Temporary uploads live under this prefix of the output URL.
TMP_PREFIX = ".tumor3d-tmp"


def _sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


class RemoteFolder:
    """An output location ``<url>`` on an object store (fsspec URL).

    Parameters
    ----------
    url : str
        ``s3://bucket/prefix``; patients go to ``<url>/<patient_id>/``.
    """

    def __init__(self, url: str) -> None:  # noqa: D107 - documented on the class
        self.url = url.rstrip("/")
        self.fs, self._base = open_fs(self.url)

    def __repr__(self) -> str:
        return f"RemoteFolder({self.url!r})"

    def key(self, relpath: str) -> str:
        """The back-end key of ``<url>/<relpath>``."""
        return f"{self._base}/{relpath}" if relpath else self._base

    def check(self) -> None:
        """Contact the endpoint once (:func:`tumor3d.storage.objectstore.check_reachable`)."""
        check_reachable(self.fs, self._base, self.url, what="output location")

    def _find(self, relpath: str) -> dict[str, dict[str, Any]]:
        """Every key under ``<url>/<relpath>/`` -> its listing entry (a fresh listing)."""
        try:
            self.fs.invalidate_cache()
            found = self.fs.find(self.key(relpath), detail=True)
        except FileNotFoundError:
            return {}
        return dict(found)

    def exists(self, relpath: str) -> bool:
        """True if the object ``<url>/<relpath>`` exists."""
        try:
            return bool(self.fs.isfile(self.key(relpath)))
        except OSError:
            return False

    def cat(self, relpath: str) -> bytes:
        """The bytes of ``<url>/<relpath>``."""
        return read_object(self.fs, self.key(relpath))


def _marker_path(name: str) -> str:
    return f"{name}/{MARKER}" if name else MARKER


def _entries(out: RemoteFolder, name: str, rels) -> dict[str, dict[str, Any] | None]:
    """The listing entry of each ``<url>/<name>/<rel>`` (None: absent).

    One listing (``name`` empty: the cohort files at the root, each asked for alone).
    """
    if name:
        listing = out._find(name)
        return {rel: listing.get(out.key(f"{name}/{rel}")) for rel in rels}
    found: dict[str, dict[str, Any] | None] = {}
    out.fs.invalidate_cache()
    for rel in rels:
        try:
            found[rel] = out.fs.info(out.key(rel))
        except OSError:
            found[rel] = None
    return found


def _etag(entry: Mapping[str, Any] | None) -> str | None:
    """The ETag of a listing entry (quotes dropped), or None where the store gives none."""
    tag = str((entry or {}).get("ETag") or (entry or {}).get("etag") or "").strip('"')
    return tag or None


def _unchanged(
    out: RemoteFolder, name: str, marker: dict[str, Any], listed: dict[str, Any]
) -> bool:
    """True if every object the marker lists is still the one published.

    Its ETag, in ``listed`` (the listing :func:`_listed_marker` checked the sizes in), is
    the marker's, or, where the marker or the store gives none, its bytes read back
    match their digests (:func:`verify_folder`). A marker written before ETags were
    kept gets the listing's then, so that the next re-run compares them instead of
    reading every object back (the listing was taken before the read-back: an object
    replaced in between shows another ETag at the next re-run, which publishes again).
    """
    etags = marker.get("etags")
    now = {rel: _etag(listed.get(rel)) for rel in marker["files"]}
    if isinstance(etags, dict) and set(etags) == set(marker["files"]) and all(now.values()):
        return now == etags
    if verify_folder(out, name):
        return False
    if listed and all(now.values()):  # best effort: the marker stays valid without them
        # not over another writer's: the marker must still be the one checked (a writer
        # that started since removed or replaced it: publish again rather than reuse)
        try:
            if json.loads(out.cat(_marker_path(name))) != marker:
                return False
        except (OSError, ValueError):
            return False
        try:
            body = json.dumps({**marker, "etags": now}, indent=1).encode()
            out.fs.pipe_file(out.key(_marker_path(name)), body)
        except Exception:  # noqa: BLE001, S110  (botocore/aiohttp raise many types)
            pass
    return True


def _listed_marker(
    out: RemoteFolder, name: str, *, check_sizes: bool = True
) -> tuple[dict[str, Any] | None, dict[str, Any]]:
    """:func:`read_marker`'s marker, and the listing entries it checked the sizes in.

    The entries are empty without ``check_sizes`` (and where the marker is not valid).
    """
    try:
        marker = json.loads(out.cat(_marker_path(name)))
    except (OSError, ValueError):
        return None, {}
    if not isinstance(marker, dict) or marker.get("format") != MARKER_FORMAT:
        return None, {}
    files = marker.get("files")
    if not isinstance(files, dict):
        return None, {}
    listed: dict[str, Any] = {}
    if check_sizes and files:
        listed = _entries(out, name, files)
        for rel, entry in listed.items():
            if entry is None or int(entry.get("size", -1)) != int(files[rel].get("size", -2)):
                return None, {}
    return marker, listed


def read_marker(out: RemoteFolder, name: str, *, check_sizes: bool = True) -> dict[str, Any] | None:
    """The marker of ``<url>/<name>/`` if the folder is published, else None.

    Valid means: the marker parses, has this module's format, and (with
    ``check_sizes``) every file it lists exists with the listed size (one
    listing; :func:`verify_folder` checks the digests).
    """
    return _listed_marker(out, name, check_sizes=check_sizes)[0]


def verify_folder(out: RemoteFolder, name: str) -> list[str]:
    """Re-read every file of a published folder against its digest.

    Returns
    -------
    list of str
        One line per problem (no marker, a missing file, a digest mismatch);
        empty when the folder is published and intact.
    """
    where = f"{out.url}/{name}" if name else out.url
    marker = read_marker(out, name, check_sizes=False)
    if marker is None:
        return [f"{where}: not published (no valid {MARKER})"]
    problems = []
    for rel, info in sorted(marker["files"].items()):
        path = f"{name}/{rel}" if name else rel
        try:
            data = out.cat(path)
        except OSError:
            problems.append(f"{out.url}/{path}: missing")
            continue
        if _sha256(data) != info.get("sha256"):
            problems.append(f"{out.url}/{path}: content does not match its sha256 in {MARKER}")
    return problems


def published_names(out: RemoteFolder) -> list[str]:
    """Sub-folders of ``<url>`` with a valid marker (published patients), sorted.

    Hidden prefixes (the temporary uploads, the artifact store) are not patients,
    nor is ``_assets`` (the viewer's shared script): a patient id starts with a
    letter or digit.
    """
    try:
        out.fs.invalidate_cache()
        entries = out.fs.ls(out.key(""), detail=True)
    except FileNotFoundError:
        return []
    names = []
    for e in entries:
        name = str(e["name"]).rstrip("/").rsplit("/", 1)[-1]
        if e.get("type") != "directory" or name.startswith((".", "_")):
            continue
        if read_marker(out, name) is not None:
            names.append(name)
    return sorted(names)


def _clean_stale_tmp(out: RemoteFolder, name: str, keep: str) -> None:
    """Remove temporary uploads of ``name`` untouched for :data:`STALE_TMP_S` (killed runs)."""
    now = time.time()
    stale: dict[str, float] = {}
    for key, entry in out._find(TMP_PREFIX).items():
        top = key[len(out.key(TMP_PREFIX)) + 1 :].split("/", 1)[0]
        if top == keep or top.rsplit(".", 1)[0] != name:
            continue
        stamp = modified_time(entry)
        stale[top] = max(stale.get(top, 0.0), 0.0 if stamp is None else stamp)  # None: stale
    for top, stamp in stale.items():
        if now - stamp > STALE_TMP_S:
            try:
                out.fs.rm(out.key(f"{TMP_PREFIX}/{top}"), recursive=True)
            except OSError:
                pass


def publish_files(
    out: RemoteFolder,
    name: str,
    files: Mapping[str, bytes | Path],
    *,
    exclusive: bool,
    key: str | None = None,
    reuse: bool = False,
) -> str:
    """Publish ``files`` (relative path -> bytes or local file) as ``<url>/<name>/``.

    The steps of the module docstring. ``name`` may be ``""`` (files at the
    root, as the cohort's ``cohort.parquet``/``.md``/``.html``), which needs
    ``exclusive=False``: then keys not in ``files`` are left alone. ``key``
    (the caller's digest of everything the folder is made from, as in
    :func:`tumor3d.storage.publish.write_publish_manifest`) is recorded in the marker;
    with ``reuse`` (every stage a cache hit), a folder whose valid marker
    (every listed file present with its size) records the same key, and whose
    objects are still the ones published (:func:`_unchanged`), is left alone:
    nothing is uploaded, although files holding run times differ.

    Returns
    -------
    str
        ``<url>/<name>``.

    Raises
    ------
    StoreError
        One line naming the object when an upload, copy or read-back fails or
        a copied object does not match the staged file's digest; no marker
        is written then.
    """
    if exclusive and not name:
        raise ValueError("an exclusive publish needs a folder name")
    where = f"{out.url}/{name}" if name else out.url
    prefix = f"{name}/" if name else ""
    data = {rel: (v.read_bytes() if isinstance(v, Path) else bytes(v)) for rel, v in files.items()}
    entries = {rel: {"sha256": _sha256(b), "size": len(b)} for rel, b in sorted(data.items())}
    current, listed = _listed_marker(out, name)
    if (
        reuse
        and key
        and current is not None
        and current.get("key") == key
        and _unchanged(out, name, current, listed)
    ):
        return where  # the same result, published, complete and intact: upload nothing
    if current is not None and current["files"] == entries and not verify_folder(out, name):
        return where  # already published with exactly these bytes (read back, intact)
    tag = f"{name or '_root'}.{os.getpid()}-{uuid.uuid4().hex[:8]}"
    tmp = f"{TMP_PREFIX}/{tag}"
    step = "upload"
    rel = ""
    try:
        for rel, b in data.items():
            out.fs.pipe_file(out.key(f"{tmp}/{rel}"), b)
        step = "unpublish"
        rel = MARKER
        try:
            out.fs.rm_file(out.key(_marker_path(name)))
        except FileNotFoundError:
            pass
        step = "copy"
        for rel in data:
            copy_object(out.fs, out.key(f"{tmp}/{rel}"), out.key(prefix + rel))
        step = "verify"
        for rel, info in entries.items():
            if _sha256(out.cat(prefix + rel)) != info["sha256"]:
                raise StoreError(
                    f"{out.url}/{prefix}{rel}: the copied object does not match the staged "
                    f"file's sha256; {where} left unpublished (no {MARKER})"
                )
        if exclusive:
            step = "remove the previous version's files"
            keep = {out.key(prefix + r) for r in data} | {out.key(_marker_path(name))}
            for obj in out._find(name):
                if obj not in keep:
                    out.fs.rm_file(obj)
        step = "list the copies"
        rel = ""
        etags = {r: _etag(e) for r, e in _entries(out, name, entries).items()}
        step = "write the marker"
        rel = MARKER
        marker = {
            "format": MARKER_FORMAT,
            "name": name,
            "files": entries,
            **({"key": key} if key else {}),
            **({"etags": etags} if all(etags.values()) else {}),
            "published_utc": utc_now(),
        }
        out.fs.pipe_file(out.key(_marker_path(name)), json.dumps(marker, indent=1).encode())
    except StoreError:
        raise
    except Exception as exc:  # botocore/aiohttp raise many types
        raise StoreError(
            f"{out.url}/{prefix}{rel}: cannot publish ({step}: {first_line(exc)[:200]}); "
            f"{where} left unpublished (no {MARKER}); a re-run completes it"
        ) from None
    finally:
        try:
            out.fs.rm(out.key(tmp), recursive=True)
        except (OSError, FileNotFoundError):
            pass
    _clean_stale_tmp(out, name or "_root", keep=tag)
    return where


def publish_folder(folder: str | Path, url: str, *, reuse: bool = False) -> str:
    """Publish a finished local folder (a staging folder) as ``<url>`` on an object store.

    ``url`` is the folder's own URL (``s3://bucket/prefix/<patient_id>``);
    every file below ``folder`` is published, relative paths kept. The key of
    the folder's publish manifest (:data:`tumor3d.storage.publish.PUBLISH_MANIFEST`),
    if any, goes into the marker; with ``reuse`` a folder published under the
    same key is left alone (:func:`publish_files`). Returns ``url``. Raises
    :class:`~tumor3d.storage.store.StoreError` as :func:`publish_files`.
    """
    from tumor3d.storage.publish import PUBLISH_MANIFEST

    root = Path(folder)
    files = {p.relative_to(root).as_posix(): p for p in sorted(root.rglob("*")) if p.is_file()}
    try:
        key = json.loads((root / PUBLISH_MANIFEST).read_text()).get("key")
    except (OSError, ValueError, AttributeError):
        key = None
    parent, name = url.rstrip("/").rsplit("/", 1)
    publish_files(
        RemoteFolder(parent), name, files, exclusive=True,
        key=key if isinstance(key, str) else None, reuse=reuse,
    )  # fmt: skip
    return url.rstrip("/")
