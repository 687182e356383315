"""Decoded volumes kept in memory by content digest: a process-wide LRU bounded by bytes.

A stage stores its volumes in the artifact store (gzip NIfTI) and the next
stages, then publishing, read them back: on a 256 x 256 x 30 phantom every
such read is a file read, a digest check, a gunzip and two copies, 16 a
patient, about a fifth of the stages' own time (issue 32 item 3). The store
keeps every volume it writes or reads here, in the form
:meth:`~tumor3d.storage.store.ArtifactStore.get_volume` returns it, so a
consumer in the same process takes it from memory instead
(:meth:`~tumor3d.storage.store.ArtifactStore.load_volume`). The store write
still happens: the cache, its keys and the published files are unchanged.

Why it can never serve a wrong value:

* the key is the artifact's content digest (kind, metadata and bytes), so
  another content is another key;
* its arrays are read-only (``flags.writeable = False``), so no consumer can
  change what the next one receives (a write raises ``ValueError``);
* what a write keeps is a copy, cast as the file stores it, so the producer
  changing its own array afterwards changes nothing here.

A Dask worker is another process with a memo of its own: it misses what
other processes stored and reads the store. Bounded by
``TUMOR3D_PRODUCT_MEMO_MIB`` (default :data:`DEFAULT_MAX_MIB`; ``0`` turns
it off); the least recently used entries go first, and an entry larger
than the bound is not kept.

>>> memo = ProductMemo(max_bytes=100)
>>> memo.put("a" * 64, (np.zeros(10, dtype=np.uint8),))
>>> memo.get("a" * 64)[0].flags.writeable, memo.nbytes
(False, 10)
>>> memo.get("b" * 64) is None
True
"""

from __future__ import annotations

import os
import threading
from collections import OrderedDict
from collections.abc import Iterable, Mapping

import numpy as np

__all__ = ["DEFAULT_MAX_MIB", "MEMO_ENV", "ProductMemo", "max_bytes_from_env", "products"]

#: Default bound of the process's memo (MiB): about four 256 x 256 x 30 patients in flight.
DEFAULT_MAX_MIB = 256
#: Environment variable giving the bound in MiB (``0``: no memo).
MEMO_ENV = "TUMOR3D_PRODUCT_MEMO_MIB"


def _nbytes(value: tuple[np.ndarray, ...]) -> int:
    return sum(int(a.nbytes) for a in value)


def _read_only(value: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    for array in value:
        array.flags.writeable = False
    return value


class ProductMemo:
    """A thread-safe LRU of tuples of read-only arrays, keyed by content digest.

    Parameters
    ----------
    max_bytes : int
        Bound on the arrays' bytes held (``0``: hold nothing).

    Attributes
    ----------
    hits, misses : int
        :meth:`get` calls that found / did not find their key.
    """

    def __init__(self, max_bytes: int) -> None:
        if max_bytes < 0:
            raise ValueError(f"max_bytes must be >= 0, got {max_bytes}")
        self.max_bytes = int(max_bytes)
        self.hits = 0
        self.misses = 0
        self._entries: OrderedDict[str, tuple[np.ndarray, ...]] = OrderedDict()
        self._bytes = 0
        self._lock = threading.Lock()

    @property
    def nbytes(self) -> int:
        """Bytes of the arrays held now."""
        return self._bytes

    def __len__(self) -> int:
        return len(self._entries)

    def get(self, digest: str) -> tuple[np.ndarray, ...] | None:
        """The value kept under ``digest`` (its arrays read-only), None if there is none."""
        with self._lock:
            value = self._entries.get(digest)
            if value is None:
                self.misses += 1
                return None
            self._entries.move_to_end(digest)
            self.hits += 1
            return value

    def put(self, digest: str, value: tuple[np.ndarray, ...]) -> None:
        """Keep ``value`` under ``digest``; its arrays are made read-only (not copied).

        The caller gives arrays nobody else writes to (the store gives its
        own copies). Older entries are dropped until the bound holds; a value
        larger than the bound is not kept.
        """
        size = _nbytes(value)
        if size > self.max_bytes:
            return
        _read_only(value)
        with self._lock:
            old = self._entries.pop(digest, None)
            if old is not None:
                self._bytes -= _nbytes(old)
            self._entries[digest] = value
            self._bytes += size
            while self._bytes > self.max_bytes:
                _, dropped = self._entries.popitem(last=False)
                self._bytes -= _nbytes(dropped)

    def discard(self, digests: Iterable[str]) -> None:
        """Forget these digests (a published patient's products); absent ones are ignored."""
        with self._lock:
            for digest in digests:
                old = self._entries.pop(digest, None)
                if old is not None:
                    self._bytes -= _nbytes(old)

    def clear(self) -> None:
        """Forget everything and reset the counters."""
        with self._lock:
            self._entries.clear()
            self._bytes = 0
            self.hits = self.misses = 0


def max_bytes_from_env(
    default_mib: int = DEFAULT_MAX_MIB, environ: Mapping[str, str] | None = None
) -> int:
    """The bound in bytes from ``TUMOR3D_PRODUCT_MEMO_MIB`` (whole MiB >= 0), else the default.

    ``environ`` defaults to :data:`os.environ`.

    >>> max_bytes_from_env(environ={MEMO_ENV: "3"})
    3145728
    >>> max_bytes_from_env(1, environ={MEMO_ENV: "lots"})
    Traceback (most recent call last):
    ...
    ValueError: TUMOR3D_PRODUCT_MEMO_MIB must be a whole number of MiB >= 0, got 'lots'
    >>> max_bytes_from_env(1, environ={})
    1048576
    """
    text = (os.environ if environ is None else environ).get(MEMO_ENV, "").strip()
    if not text:
        return default_mib * 1024 * 1024
    if not text.isdigit():
        raise ValueError(f"{MEMO_ENV} must be a whole number of MiB >= 0, got {text!r}")
    return int(text) * 1024 * 1024


_PROCESS_MEMO: list[ProductMemo] = []
_PROCESS_LOCK = threading.Lock()


def products() -> ProductMemo:
    """The process's memo of decoded volumes (filled and read by the artifact store).

    Made on first use with the bound of :func:`max_bytes_from_env`, so a bad
    ``TUMOR3D_PRODUCT_MEMO_MIB`` fails the first stage that stores a volume,
    with one line naming the variable, not every import.
    """
    if not _PROCESS_MEMO:
        with _PROCESS_LOCK:
            if not _PROCESS_MEMO:
                _PROCESS_MEMO.append(ProductMemo(max_bytes_from_env()))
    return _PROCESS_MEMO[0]
