"""The artifact store on an object store (``s3://bucket/prefix``, any fsspec URL).

:class:`ObjectStore` is a backend beside the local
:class:`~tumor3d.storage.store.ArtifactStore` with the same interface and the same
digests and object names (``<url>/objects/<d[:2]>/<d>.<suffix>``), so cache
keys, :class:`~tumor3d.storage.refs.ArtifactRef` values and stage results do not
depend on where the store lives. Only the file operations under the raw-bytes
layer differ (reading, writing and quarantining one object, the repair log, the
sweep); the rules of ``put_bytes`` and ``get_bytes`` and the typed helpers
(``put_volume``, ``get_mesh``, ...) are the local class's own.

* **Atomic publication**: on S3 an object is written by one PUT, which is
  all-or-nothing (the object appears complete or not at all, a multipart upload
  only when completed). On other fsspec back-ends, which promise no such thing,
  it is written under a temporary key ``<url>/tmp/<name>.<random>``, then
  copied to its final key and the temporary key removed; a writer killed
  before the copy leaves only a ``tmp/`` key, never a partial object under a
  final name.
* **One request where one will do** (:func:`read_object`, :func:`copy_object`):
  every S3 request is a round trip, billed. A new artifact costs a GET (is it
  there?) and a PUT, a read one GET: no HEAD to size the object first, no
  listing to tell a key from a folder, no copy.
* **Digest verified on read**: a mismatch moves the object to
  ``<url>/quarantine/<name>.<utc time>-<random>`` and raises
  :class:`~tumor3d.storage.refs.CorruptArtifactError`, as locally. Repairs are
  recorded as one small JSON object each under ``<url>/repairs/`` (object
  stores have no append).
* **Prefect's results** (the cached stage outputs) live under
  ``<url>/prefect-results`` through Prefect's ``RemoteFileSystem``
  (:func:`tumor3d.tasks.runner.result_storage_for`), so every worker finds every
  cache hit.

Credentials and endpoint come from the usual environment of the back-end
(for S3: ``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY``, ``AWS_REGION``, and
``AWS_ENDPOINT_URL`` for an S3-compatible server such as MinIO), so Dask
workers given the same environment open the same store.
:func:`open_store` picks the backend from the location; :meth:`ObjectStore.check`
contacts the endpoint once, before any patient starts.
"""

from __future__ import annotations

import functools
import inspect
import json
import os
import time
import uuid
from dataclasses import asdict
from pathlib import Path
from typing import Any

from tumor3d.storage.atomic import STALE_TMP_S
from tumor3d.storage.refs import ArtifactRef, Repair, StoreError
from tumor3d.storage.store import ArtifactStore, check_own_object

__all__ = [
    "STORE_DIRNAME",
    "ObjectStore",
    "check_reachable",
    "default_store_location",
    "first_line",
    "is_url",
    "modified_time",
    "open_fs",
    "open_store",
    "put_is_atomic",
    "read_object",
    "copy_object",
]

#: The artifact store's folder inside the output when no ``--store`` is given.
STORE_DIRNAME = ".tumor3d-store"

#: Seconds to wait for an S3 endpoint to accept a connection.
S3_CONNECT_TIMEOUT_S = 5
#: botocore's attempts at an S3 request (inside each of s3fs's own retries).
S3_MAX_ATTEMPTS = 3
#: Pages of unfinished multipart uploads one sweep reads (S3 lists up to 1,000 a page).
UPLOAD_PAGES = 100


def is_url(location: str | os.PathLike[str]) -> bool:
    """True for ``scheme://...`` locations (an object store), False for paths."""
    text = os.fspath(location)
    return "://" in text and not text.startswith("file://")


def default_store_location(out_dir: str | os.PathLike[str]) -> Path | str:
    """The artifact store used when none is given: ``<out_dir>/.tumor3d-store``.

    A URL for an object-store ``out_dir`` (``s3://bucket/x/.tumor3d-store``).
    The one definition of the default (every command and flow uses it).

    >>> str(default_store_location("out"))
    'out/.tumor3d-store'
    >>> default_store_location("s3://bucket/run/")
    's3://bucket/run/.tumor3d-store'
    """
    if is_url(out_dir):
        return f"{os.fspath(out_dir).rstrip('/')}/{STORE_DIRNAME}"
    return Path(out_dir) / STORE_DIRNAME


def open_store(location: str | os.PathLike[str]) -> ArtifactStore:
    """The artifact store at ``location``: :class:`ObjectStore` for a URL, else local.

    Cheap (no network call): tasks call it for every stage.
    """
    if is_url(location):
        return ObjectStore(os.fspath(location))
    return ArtifactStore(location)


def modified_time(entry: dict[str, Any]) -> float | None:
    """An fsspec listing entry's modification time (seconds since the epoch), or None.

    Back-ends name it differently: ``LastModified`` (s3fs), ``mtime`` (local),
    ``updated`` (gcsfs), ``last_modified`` (adlfs); a value that is neither a
    datetime nor a number reads as None.

    >>> modified_time({"mtime": 12.5}), modified_time({"updated": "yesterday"})
    (12.5, None)
    """
    for k in ("LastModified", "mtime", "updated", "last_modified"):
        v = entry.get(k)
        if v is None:
            continue
        try:
            return float(v.timestamp()) if hasattr(v, "timestamp") else float(v)
        except (TypeError, ValueError):
            return None
    return None


def first_line(exc: BaseException) -> str:
    r"""The first line of an exception's message, or its type's name when it has none.

    >>> first_line(OSError("timed out\nretries: 3"))
    'timed out'
    """
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def _storage_options(protocol: str) -> dict[str, Any]:
    if protocol in ("s3", "s3a"):
        endpoint = os.environ.get("AWS_ENDPOINT_URL_S3") or os.environ.get("AWS_ENDPOINT_URL")
        return {
            # explicit, so that fsspec's instance cache keys on the endpoint too
            **({"endpoint_url": endpoint} if endpoint else {}),
            # another worker may have written an object since we listed: never trust a listing
            "use_listings_cache": False,
            "config_kwargs": {
                "connect_timeout": S3_CONNECT_TIMEOUT_S,
                "read_timeout": 120,
                "retries": {"max_attempts": S3_MAX_ATTEMPTS, "mode": "standard"},
            },
        }
    return {}


def open_fs(url: str) -> tuple[Any, str]:
    """The fsspec file system and root key of ``url`` (the same options as the store's).

    Raises
    ------
    InputError
        If the URL's scheme has no fsspec back-end installed.
    """
    from tumor3d.errors import InputError

    try:
        import fsspec
    except ImportError:  # pragma: no cover - fsspec comes with Prefect
        raise InputError("an object store needs fsspec", url) from None
    url = url.rstrip("/")
    protocol = url.split("://", 1)[0]
    try:
        fs, base = fsspec.core.url_to_fs(url, **_storage_options(protocol))
    except (ImportError, ValueError) as exc:
        raise InputError(
            f"cannot open this location ({first_line(exc)}); for s3:// install "
            "'tumor3d[s3]' (s3fs)",
            url,
        ) from None
    return fs, base.rstrip("/")


#: fsspec protocols whose PUT is all-or-nothing and which have no folders (s3fs).
ATOMIC_PUT_PROTOCOLS = frozenset({"s3", "s3a"})


def put_is_atomic(fs: Any) -> bool:
    """True if one write of ``fs`` makes an object appear whole or not at all (S3).

    >>> import fsspec
    >>> put_is_atomic(fsspec.filesystem("memory"))
    False
    """
    protocol = fs.protocol if isinstance(fs.protocol, (tuple, list)) else (fs.protocol,)
    return not ATOMIC_PUT_PROTOCOLS.isdisjoint(protocol)


@functools.cache
def _sizes_before_reading(fs_type: type) -> bool:
    """True if this s3fs's ``cat_file`` sizes an object before reading it.

    s3fs 2026.3 and later do (and take ``max_concurrency``); earlier ones read in one
    GET and refuse the keyword.
    """
    reader = getattr(fs_type, "_cat_file", None)
    try:
        return reader is not None and "max_concurrency" in inspect.signature(reader).parameters
    except (TypeError, ValueError):
        return False


def read_object(fs: Any, key: str) -> bytes:
    """The bytes of the object ``key``: one GET on S3.

    s3fs's ``cat_file`` (since 2026.3) first asks an object's size (a HEAD, and a
    listing when the key is missing) to read a large one in parallel ranges; the
    artifacts and records here are read whole, in one request.

    Raises
    ------
    FileNotFoundError
        If there is no such object.
    """
    if put_is_atomic(fs) and _sizes_before_reading(type(fs)):
        return fs.cat_file(key, max_concurrency=1)
    return fs.cat_file(key)


def copy_object(fs: Any, src: str, dst: str) -> None:
    """Copy one object to another key, server side.

    ``fs.copy`` first expands both paths as globs and folders (listings); the keys
    here are single objects.
    """
    fs.cp_file(src, dst)


def check_reachable(fs: Any, base: str, url: str, *, what: str = "artifact store") -> None:
    """Contact the endpoint once: list the bucket of ``base``.

    Raises
    ------
    StoreError
        One line naming ``url`` when the endpoint, bucket or credentials do
        not work (call it before any patient starts).
    """
    bucket = base.split("/", 1)[0]
    try:
        fs.ls(bucket, detail=False)  # a real request (exists() hides errors)
    except FileNotFoundError:
        raise StoreError(f"{url}: the bucket {bucket!r} does not exist") from None
    except Exception as exc:  # botocore/aiohttp raise many types; all mean "unreachable"
        raise StoreError(
            f"{url}: cannot reach the {what} ({type(exc).__name__}: "
            f"{first_line(exc)[:200]}); check AWS_ENDPOINT_URL and the credentials"
        ) from None


class ObjectStore(ArtifactStore):
    """Content-addressed artifacts under an fsspec URL (``s3://bucket/prefix``).

    Parameters
    ----------
    url : str
        The store's root URL; nothing is created until the first write.

    Raises
    ------
    InputError
        If the URL's scheme has no fsspec back-end installed (``s3`` needs
        ``s3fs``: ``pip install 'tumor3d[s3]'``).
    """

    def __init__(self, url: str) -> None:  # noqa: D107 - documented on the class
        # The local constructor (a folder, mkdir) does not apply; the attributes it sets do.
        self.url = url.rstrip("/")
        self.fs, self._base = open_fs(self.url)
        self.root = self.url  # type: ignore[assignment]  # a URL, not a Path
        self.repairs: list[Repair] = []

    def __repr__(self) -> str:
        return f"ObjectStore({self.url!r})"

    def __reduce__(self) -> tuple[Any, ...]:
        return (ObjectStore, (self.url,))

    # -- locations ---------------------------------------------------------
    def _key(self, relpath: str) -> str:
        return f"{self._base}/{relpath}"

    def _url_of(self, key: str) -> str:
        """The URL of ``key``, a key under this store (:meth:`_key`'s inverse)."""
        return f"{self.url}/{key[len(self._base) + 1 :]}"

    def path(self, ref: ArtifactRef) -> str:  # type: ignore[override]
        """URL of an artifact's object."""
        return f"{self.url}/{ref.relpath}"

    def exists(self, ref: ArtifactRef) -> bool:
        """True if the artifact's object is present."""
        try:
            return bool(self.fs.isfile(self._key(ref.relpath)))
        except OSError:
            return False

    @property
    def storage_options(self) -> dict[str, Any]:
        """The fsspec options this store opens its URL with (JSON-able)."""
        return _storage_options(self.url.split("://", 1)[0])

    def check(self) -> None:
        """Contact the endpoint once: list the store's root.

        Raises
        ------
        StoreError
            One line naming the URL when the endpoint, bucket or credentials
            do not work (call it before any patient starts).
        """
        check_reachable(self.fs, self._base, self.url)

    # -- healing -----------------------------------------------------------
    def _record(self, repair: Repair) -> Repair:
        self.repairs.append(repair)
        name = f"repairs/{time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())}-{uuid.uuid4().hex}.json"
        try:
            self.fs.pipe_file(self._key(name), json.dumps(asdict(repair), sort_keys=True).encode())
        except OSError:
            pass  # the log is informative; the repair itself is done
        return repair

    def _quarantine(self, relpath: str, detail: str) -> Repair:
        check_own_object(relpath, self.url)
        moved: str | None = self._quarantine_relpath(Path(relpath).name)
        try:
            copy_object(self.fs, self._key(relpath), self._key(moved))
            self.fs.rm_file(self._key(relpath))
        except FileNotFoundError:  # another worker moved or rewrote it first
            moved = None
        return self._quarantined(relpath, detail, moved)

    def read_repairs(self) -> list[Repair]:
        """Every repair recorded under ``<url>/repairs/``, oldest first."""
        try:
            keys = sorted(self.fs.find(self._key("repairs")))
        except FileNotFoundError:
            return []
        out = []
        for key in keys:
            try:
                out.append(Repair(**json.loads(read_object(self.fs, key))))
            except (OSError, ValueError, TypeError):
                continue
        return out

    # -- the file operations under the raw-bytes layer ---------------------
    def _existing_bytes(self, relpath: str) -> bytes | None:
        try:
            return read_object(self.fs, self._key(relpath))
        except OSError:  # absent (FileNotFoundError) or unreadable
            return None

    def _write_object(self, relpath: str, data: bytes) -> None:
        """Write ``relpath`` (:meth:`_write_atomically`); else :class:`StoreError` naming it."""
        try:
            self._write_atomically(relpath, data)
        except Exception as exc:  # a denied PUT, an endpoint gone mid-run, ...
            raise StoreError(
                f"{self.url}/{relpath}: cannot write the artifact ({first_line(exc)[:200]})"
            ) from None

    def _write_atomically(self, relpath: str, data: bytes) -> None:
        """One PUT where a PUT is all-or-nothing (S3), else a temporary key and a copy.

        Elsewhere the bytes go under a temporary key, are copied to the final key,
        and the temporary key is removed.
        """
        if put_is_atomic(self.fs):
            self.fs.pipe_file(self._key(relpath), data)
            return
        tmp = self._key(f"tmp/{Path(relpath).name}.{os.getpid()}-{uuid.uuid4().hex[:8]}")
        try:
            self.fs.pipe_file(tmp, data)
            copy_object(self.fs, tmp, self._key(relpath))
        finally:
            try:
                self.fs.rm_file(tmp)
            except (OSError, FileNotFoundError):
                pass

    def _read_object(self, ref: ArtifactRef) -> bytes:
        url = self.path(ref)
        try:
            return read_object(self.fs, self._key(ref.relpath))
        except FileNotFoundError:
            raise StoreError(f"artifact {ref.kind} {ref.digest[:12]} is missing: {url}") from None
        except Exception as exc:
            raise StoreError(f"{url}: cannot read the artifact ({first_line(exc)[:200]})") from None

    def clean_stale_tmp(self, *, max_age_s: float = STALE_TMP_S) -> list[str]:
        """Remove temporary keys (``tmp/``) untouched for ``max_age_s``: killed writers'.

        A remote writer's process cannot be asked whether it is alive, so a
        temporary key is removed by age only (a write takes seconds). On S3, where
        one PUT writes an object, a killed writer of a large one (s3fs uploads from
        100 MiB in parts) leaves an unfinished multipart upload instead: invisible,
        billed, and aborted here by the same age.

        Returns
        -------
        list of str
            The URLs removed (an aborted upload: its object's URL).
        """
        removed = self._abort_stale_uploads(max_age_s) if put_is_atomic(self.fs) else []
        try:
            entries = self.fs.find(self._key("tmp"), detail=True)
        except Exception:  # housekeeping: an unlistable store is left as it is
            return removed
        now = time.time()
        for key, entry in entries.items():
            stamp = modified_time(entry)
            if stamp is None or now - stamp <= max_age_s:  # no age to judge by: kept
                continue
            try:
                self.fs.rm_file(key)
            except Exception:  # housekeeping: a key that cannot be removed is left as it is
                continue
            removed.append(self._url_of(key))
        return removed

    def _abort_stale_uploads(self, max_age_s: float) -> list[str]:
        """Abort the store's multipart uploads started more than ``max_age_s`` ago.

        S3 lists them 1,000 a page; the sweep reads up to :data:`UPLOAD_PAGES` pages (a
        store with more left over reads the rest at its next sweep).
        """
        bucket, _, prefix = self._base.partition("/")
        listing = {"Bucket": bucket, "Prefix": f"{prefix}/" if prefix else ""}
        removed: list[str] = []
        now = time.time()
        after: dict[str, str] = {}  # the (key, upload id) a page starts after
        for _ in range(UPLOAD_PAGES):
            try:
                listed = self.fs.call_s3("list_multipart_uploads", **listing, **after)
            except Exception:  # housekeeping: an endpoint that cannot list them is left
                return removed
            for upload in listed.get("Uploads", []):
                started = modified_time({"LastModified": upload.get("Initiated")})
                if started is None or now - started <= max_age_s:
                    continue
                try:
                    self.fs.call_s3(
                        "abort_multipart_upload",
                        Bucket=bucket, Key=upload["Key"], UploadId=upload["UploadId"],
                    )  # fmt: skip
                except Exception:  # housekeeping: an upload that cannot be aborted is left
                    continue
                removed.append(self._url_of(f"{bucket}/{upload['Key']}"))
            if not listed.get("IsTruncated") or not listed.get("NextKeyMarker"):
                break
            after = {
                "KeyMarker": listed["NextKeyMarker"],
                "UploadIdMarker": listed.get("NextUploadIdMarker", ""),
            }
        return removed
