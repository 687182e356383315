"""What the artifact store hands out and reports: references, repairs and errors.

Tasks pass :class:`ArtifactRef` values around (a few hundred bytes), never
arrays; a reference names its content by digest, computed over
:func:`canonical_dumps` of its metadata. A store that finds or replaces a bad
object says so with a :class:`Repair`; a read that finds one raises
:class:`CorruptArtifactError`, and every other store failure is a
:class:`StoreError`. The stores themselves are :mod:`tumor3d.storage.store`
(a folder) and :mod:`tumor3d.storage.objectstore` (an object store).
"""

from __future__ import annotations

import json
import re
import time
from dataclasses import dataclass
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, model_validator

from tumor3d.errors import Tumor3DError

__all__ = [
    "ArtifactRef",
    "CorruptArtifactError",
    "Repair",
    "StoreError",
    "canonical_dumps",
    "check_object_relpath",
    "object_relpath",
    "utc_now",
]


class StoreError(Tumor3DError):
    """A missing, corrupted or unwritable artifact (an environment problem, not bad input)."""


@dataclass(frozen=True)
class Repair:
    """One repair the store made.

    Parameters
    ----------
    relpath : str
        The object's path relative to the store root.
    action : str
        ``"quarantined"`` (content did not match the digest; moved aside) or
        ``"rewritten"`` (an existing object with other bytes was replaced
        by :meth:`~tumor3d.storage.store.ArtifactStore.put_bytes`).
    detail : str
        One line for a log.
    quarantined_to : str or None
        Where the bad file now is (relative to the root), if quarantined.
    time_utc : str
        ISO 8601 time of the repair.
    """

    relpath: str
    action: str
    detail: str
    quarantined_to: str | None = None
    time_utc: str = ""


class CorruptArtifactError(StoreError):
    """An artifact whose content did not match its digest; it has been quarantined.

    The stage that produced ``ref`` should be run again (its output will be
    written afresh). ``repair`` says where the bad file went.
    """

    def __init__(self, message: str, *, ref: ArtifactRef, repair: Repair) -> None:
        super().__init__(message)
        self.ref = ref
        self.repair = repair


class ArtifactRef(BaseModel):
    """A small, JSON-serialisable reference to an artifact in the store.

    Parameters
    ----------
    kind : str
        ``scan``, ``image``, ``mask``, ``mesh``, ``table``, ``png`` or ``json``.
    digest : str
        Hex SHA-256 of kind, canonical metadata and bytes.
    relpath : str
        Path of the file relative to the store root: ``objects/<the digest's first two
        characters>/<digest><suffix>`` (:func:`object_relpath`), the only path a store
        writes; any other is refused (a record read from a shared store that named
        ``../x`` or an absolute path would steer the tool to a file outside the store).
    metadata : dict
        Canonical, JSON-able description (shape, dtype, affine, ...).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: str
    digest: str = Field(pattern=r"^[0-9a-f]{64}$")
    relpath: str
    metadata: dict[str, Any] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _relpath_is_its_digests(self) -> ArtifactRef:
        check_object_relpath(self.relpath, self.digest)
        return self


#: A file name suffix of a stored object: up to two lower-case extensions (``.nii.gz``).
_SUFFIX = re.compile(r"(\.[a-z0-9]{1,8}){1,2}")


def object_relpath(digest: str, suffix: str) -> str:
    """Where a store keeps the object of ``digest``: ``objects/<digest[:2]>/<digest><suffix>``.

    >>> object_relpath("ab" + "0" * 62, ".nii.gz")[:12]
    'objects/ab/a'
    """
    return f"objects/{digest[:2]}/{digest}{suffix}"


def check_object_relpath(relpath: str, digest: str) -> None:
    """``ValueError`` unless ``relpath`` is :func:`object_relpath` of ``digest`` and a suffix.

    >>> d = "ab" + "0" * 62
    >>> check_object_relpath(object_relpath(d, ".ply"), d)
    >>> check_object_relpath("../../in/scan.nii.gz", d)
    Traceback (most recent call last):
    ValueError: relpath '../../in/scan.nii.gz' is not where the store keeps object ab0000000000...
    """
    base = object_relpath(digest, "")
    if not (relpath.startswith(base) and _SUFFIX.fullmatch(relpath[len(base) :])):
        raise ValueError(
            f"relpath {relpath!r} is not where the store keeps object {digest[:12]}..."
        )


def canonical_dumps(obj: Any) -> str:
    """JSON with sorted keys and no whitespace; NaN is refused."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)


def utc_now() -> str:
    """The time now in UTC, to the second, as the records write it (``2026-12-06T03:12:00Z``)."""
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
