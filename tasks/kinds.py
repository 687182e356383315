"""Artifact kinds: how a stage's declared inputs are loaded and its outputs stored.

One table, :data:`KINDS`: kind -> :class:`Kind` (the store's getter and
putter for it). The stage decorator (:func:`tumor3d.tasks.spec.stage`) loads
every declared input through it before calling the adapter and stores every
product the adapter returns under its declared kind, so that an adapter only
calls its core function.

* ``scan``, ``image``, ``mask`` load as :class:`Volume` ``(array (z, y, x),
  affine)`` (a mask as bool), read-only arrays taken from the process's memo
  of decoded volumes when this process stored or read them before
  (:meth:`~tumor3d.storage.store.ArtifactStore.load_volume`); a ``scan`` is
  stored from a :class:`~tumor3d.imaging.scan.Scan`, the others from a
  :class:`Volume`;
* ``mesh`` as :class:`~tumor3d.geometry.mesh.Mesh`; ``table`` as a DataFrame
  (stored from a DataFrame or a list of records);
* ``png`` (an RGB array), ``gif`` and ``training-rows`` (bytes) are stored
  only.

A product may carry metadata of its own (:class:`Tagged`). An input declared
``load=False`` arrives as an :class:`Artifact` handle instead: its metadata
at once, its content on :meth:`Artifact.load` (for an input used only for its
metadata, or only on one branch).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from fnmatch import fnmatch
from typing import Any

import numpy as np

from tumor3d.storage.store import ArtifactRef, ArtifactStore

__all__ = ["KINDS", "Artifact", "Kind", "Tagged", "Volume", "declared_kind"]


@dataclass(frozen=True)
class Volume:
    """A volume as a stage sees it: ``(z, y, x)`` array and its affine (``(x, y, z, 1)`` -> RAS).

    ``dtype``: stored as this type (default: the array's, bool as uint8).
    Unpacks as ``array, affine``.
    """

    array: np.ndarray
    affine: np.ndarray
    dtype: str | None = None

    def __iter__(self) -> Iterator[np.ndarray]:
        return iter((self.array, self.affine))


@dataclass(frozen=True)
class Tagged:
    """A product with metadata of its own (in its artifact's metadata, so in its digest)."""

    value: Any
    metadata: Mapping[str, Any]


@dataclass(frozen=True)
class Kind:
    """How one kind of artifact is loaded (``None``: never an input) and stored."""

    put: Callable[[ArtifactStore, Any, dict[str, Any] | None], ArtifactRef]
    get: Callable[[ArtifactStore, ArtifactRef], Any] | None = None


def _get_volume(store: ArtifactStore, ref: ArtifactRef) -> Volume:
    # read-only arrays, from memory when this process stored or read the volume before
    array, affine = store.load_volume(ref)
    return Volume(array, affine)


def _put_volume(kind: str) -> Callable[[ArtifactStore, Any, dict[str, Any] | None], ArtifactRef]:
    def put(store: ArtifactStore, value: Volume, metadata: dict[str, Any] | None) -> ArtifactRef:
        return store.put_volume(
            value.array, value.affine, kind=kind, dtype=value.dtype, extra=metadata
        )

    return put


def _put_bytes(kind: str, suffix: str) -> Callable[..., ArtifactRef]:
    def put(store: ArtifactStore, value: bytes, metadata: dict[str, Any] | None) -> ArtifactRef:
        return store.put_bytes(value, kind=kind, suffix=suffix, metadata=metadata)

    return put


#: Artifact kind -> its getter and putter.
KINDS: dict[str, Kind] = {
    "scan": Kind(put=lambda s, v, m: s.put_scan(v), get=_get_volume),
    "image": Kind(put=_put_volume("image"), get=_get_volume),
    "mask": Kind(put=_put_volume("mask"), get=_get_volume),
    "mesh": Kind(put=lambda s, v, m: s.put_mesh(v, extra=m), get=lambda s, r: s.get_mesh(r)),
    "table": Kind(put=lambda s, v, m: s.put_table(v), get=lambda s, r: s.get_table(r)),
    "png": Kind(put=lambda s, v, m: s.put_png(v, extra=m)),
    "gif": Kind(put=_put_bytes("gif", ".gif")),
    "training-rows": Kind(put=_put_bytes("training-rows", ".npz")),
    # a user's trained models (segment.learned_models), packed: tumor3d.learned.bundle
    "models": Kind(put=_put_bytes("models", ".npz"), get=lambda s, r: s.get_bytes(r)),
}


@dataclass(frozen=True)
class Artifact:
    """An input artifact not loaded yet: its reference, its metadata, :meth:`load`."""

    ref: ArtifactRef
    store: ArtifactStore

    @property
    def metadata(self) -> dict[str, Any]:
        """The artifact's metadata (no loading)."""
        return self.ref.metadata

    def load(self) -> Any:
        """The content, as an input of its kind is loaded (:data:`KINDS`)."""
        return load(self.store, self.ref)


def load(store: ArtifactStore, ref: ArtifactRef) -> Any:
    """An artifact's content by its kind (:data:`KINDS`)."""
    getter = KINDS[ref.kind].get
    if getter is None:
        raise TypeError(f"an artifact of kind {ref.kind!r} is never a stage input")
    return getter(store, ref)


def store_product(store: ArtifactStore, kind: str, value: Any) -> ArtifactRef:
    """Store one product under its declared ``kind`` (a :class:`Tagged` with its metadata)."""
    metadata = None
    if isinstance(value, Tagged):
        value, metadata = value.value, dict(value.metadata)
    return KINDS[kind].put(store, value, metadata)


def declared_kind(outputs: Mapping[str, str], name: str) -> str | None:
    """The kind ``outputs`` declares for product ``name`` (exact, else an ``fnmatch`` pattern)."""
    if name in outputs:
        return outputs[name]
    return next((k for pattern, k in outputs.items() if fnmatch(name, pattern)), None)
