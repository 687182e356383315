"""The content-addressed artifact store in a folder: :class:`ArtifactStore`.

Each artifact is a file under ``<root>/objects/<d[:2]>/<d>.<suffix>`` where
``d`` is the SHA-256 digest of the artifact's kind, its canonical metadata
(dtype, shape, spacing and affine for images) and its bytes. Files are
written under a temporary name in the same folder, flushed and renamed
(:func:`~tumor3d.storage.atomic.atomic_write_bytes`), so a crash never leaves
a half-written artifact under its final name. Nothing is ever unpickled:
images are NIfTI, meshes PLY, tables parquet, renders PNG, small records JSON.

This room holds the store itself: its raw-bytes layer (the digest rule, the
write that repairs and the read that verifies, over a few file operations an
object-store back-end replaces: :mod:`tumor3d.storage.objectstore`), its
healing and its typed helpers (volumes, scans, meshes, tables, PNG, JSON).
The references, repairs and errors it hands out are
:mod:`tumor3d.storage.refs`; atomic writes and the sweep of what killed
writers leave are :mod:`tumor3d.storage.atomic`. Both are re-exported here
(:data:`__all__`), where most callers import them from.

A store that heals
------------------
Reads verify the digest. A file whose content no longer matches its digest
(bit rot, a hand edit) is *quarantined*: moved to
``<root>/quarantine/<name>.<utc time>-<random>`` (kept for inspection, never
deleted) and a :class:`CorruptArtifactError` is raised, so that the stage
that made it can be run again and write it afresh. :meth:`ArtifactStore.verify`
does the same check without raising (for a cached stage's outputs).
:meth:`ArtifactStore.put_bytes` rewrites an existing object whose bytes
differ from the new ones (same size or not). Every repair is a
:class:`Repair`, kept in :attr:`ArtifactStore.repairs` and appended as one
JSON line to ``<root>/repairs.jsonl``, so the task layer can say what was
repaired.

A writer killed mid-write (``kill -9``, a lost Dask worker) leaves its
temporary file, never a final object; :meth:`ArtifactStore.clean_stale_tmp`
(run at the end of every patient and cohort flow) removes those whose
process is gone.

Tasks pass :class:`ArtifactRef` values around (a few hundred bytes), never
arrays.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
import uuid
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from tumor3d.errors import InputError, os_error_path, os_error_text
from tumor3d.geometry.mesh import Mesh
from tumor3d.imaging.scan import Scan, SourceGrid
from tumor3d.storage import formats, nifti
from tumor3d.storage.atomic import (
    HOST_TAG,
    STALE_TMP_S,
    atomic_write_bytes,
    check_writable_dir,
    process_alive,
    remove_stale_tmp,
    writer_gone,
)
from tumor3d.storage.product_memo import products
from tumor3d.storage.refs import (
    ArtifactRef,
    CorruptArtifactError,
    Repair,
    StoreError,
    canonical_dumps,
    check_object_relpath,
    object_relpath,
    utc_now,
)

__all__ = [
    "ArtifactRef",
    "ArtifactStore",
    "CorruptArtifactError",
    "HOST_TAG",
    "Repair",
    "STALE_TMP_S",
    "StoreError",
    "atomic_write_bytes",
    "canonical_dumps",
    "check_own_object",
    "check_writable_dir",
    "process_alive",
    "utc_now",
    "writer_gone",
]

_DIGEST_PREFIX = b"tumor3d-artifact-v1\0"


def _affine_list(affine: np.ndarray) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.asarray(affine, dtype=np.float64)]


def _stored_affine(affine: np.ndarray) -> np.ndarray:
    """The affine a stored volume reads back with: NIfTI keeps the sform as float32."""
    return np.asarray(affine, dtype=np.float64).astype(np.float32).astype(np.float64)


def check_own_object(relpath: str, where: object) -> None:
    """:class:`StoreError` unless ``relpath`` lies in the store's ``objects/``.

    Relative, no ``..``: a store moves or rewrites nothing else, whatever a record names.

    >>> check_own_object("objects/ab/abc.ply", "/s")
    >>> check_own_object("../in/scan.nii.gz", "/s")
    Traceback (most recent call last):
    tumor3d.storage.refs.StoreError: '../in/scan.nii.gz' is not an object of the store /s: not moved
    """
    parts = Path(relpath).parts
    if Path(relpath).is_absolute() or ".." in parts or parts[:1] != ("objects",) or len(parts) < 3:
        raise StoreError(f"{relpath!r} is not an object of the store {where}: not moved")


class ArtifactStore:
    """A folder of content-addressed artifacts.

    Parameters
    ----------
    root : path
        The store folder; created if missing.

    Raises
    ------
    InputError
        If ``root`` is a file or lies below one (one line naming it).
    StoreError
        If it cannot be created for another reason: no permission, a
        read-only mount, a full disk (an environment error).

    Notes
    -----
    :meth:`put_bytes` and :meth:`get_bytes` hold the rules every back-end
    shares (the digest, a rewrite of other bytes recorded, a mismatch on read
    quarantined and raised). They reach the stored bytes through a few file
    operations, ``_existing_bytes``, ``_write_object``, ``_read_object`` and
    ``_quarantine``, with ``_record``, :meth:`read_repairs`,
    :meth:`clean_stale_tmp`, :meth:`path` and :meth:`exists`: a back-end
    elsewhere (:class:`~tumor3d.storage.objectstore.ObjectStore`) overrides
    those and inherits the rest.
    """

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root).resolve()
        if self.root.exists() and not self.root.is_dir():
            raise InputError("the artifact store must be a folder, but this is a file", self.root)
        try:
            (self.root / "objects").mkdir(parents=True, exist_ok=True)
        except (NotADirectoryError, FileExistsError) as exc:  # a path component is a file
            raise InputError(
                f"cannot create the artifact store ({os_error_text(exc)})",
                os_error_path(exc, self.root),
            ) from None
        except OSError as exc:  # no permission, a read-only mount, a full disk
            raise StoreError(
                f"{os_error_path(exc, self.root)}: cannot create the artifact store "
                f"({os_error_text(exc)})"
            ) from None
        self.repairs: list[Repair] = []
        """Repairs made through this instance (also in ``<root>/repairs.jsonl``)."""

    # -- healing -----------------------------------------------------------
    def _record(self, repair: Repair) -> Repair:
        self.repairs.append(repair)
        line = json.dumps(asdict(repair), sort_keys=True) + "\n"
        try:
            with open(self.root / "repairs.jsonl", "a", encoding="utf-8") as fh:
                fh.write(line)
        except OSError:
            pass  # the log is informative; the repair itself is done
        return repair

    def _quarantine(self, relpath: str, detail: str) -> Repair:
        """Move a bad object aside (never delete it) so that it can be rewritten.

        Only an object of the store's own layout (``objects/...``, no ``..``) is ever
        moved: :class:`StoreError` otherwise, nothing touched.
        """
        check_own_object(relpath, self.root)
        path = self.root / relpath
        target = self.root / self._quarantine_relpath(path.name)
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.replace(path, target)
            moved: str | None = target.relative_to(self.root).as_posix()
        except FileNotFoundError:  # another process moved or rewrote it first
            moved = None
        return self._quarantined(path.relative_to(self.root).as_posix(), detail, moved)

    @staticmethod
    def _quarantine_relpath(name: str) -> str:
        """Where a bad object named ``name`` goes: ``quarantine/<name>.<utc time>-<random>``."""
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        return f"quarantine/{name}.{stamp}-{uuid.uuid4().hex[:8]}"

    def _quarantined(self, relpath: str, detail: str, moved: str | None) -> Repair:
        """Record the quarantine of ``relpath``, moved to ``moved`` (None: gone already)."""
        return self._record(
            Repair(
                relpath=relpath,
                action="quarantined",
                detail=detail,
                quarantined_to=moved,
                time_utc=utc_now(),
            )
        )

    def clean_stale_tmp(self, *, max_age_s: float = STALE_TMP_S) -> list[str]:
        """Remove temporary object files left by writers that were killed.

        A process killed while writing an object (``kill -9``, a Dask worker
        lost mid-stage) cannot remove its temporary file. One is removed here
        when it was written under this machine's and pid namespace's
        :data:`HOST_TAG` by a process that no longer exists, or when untouched
        for ``max_age_s`` (written elsewhere: a store shared over a network
        file system; or its pid since reused). A live writer's file is never
        touched; an object under its final name never is. Housekeeping: a file
        that cannot be examined or removed (another user's, a read-only store)
        is left as it is.

        Returns
        -------
        list of str
            The files removed.
        """
        now = time.time()
        try:
            found = list((self.root / "objects").glob("*/.*.tmp-*"))
        except OSError:
            return []
        return remove_stale_tmp(found, now=now, max_age_s=max_age_s)

    def read_repairs(self) -> list[Repair]:
        """Every repair recorded in ``<root>/repairs.jsonl``, oldest first.

        Tasks open their own store instances, so a flow that wants to say
        what a run repaired compares ``len(store.read_repairs())`` before and
        after the run. Unparsable lines (a torn write) are skipped.
        """
        path = self.root / "repairs.jsonl"
        try:
            lines = path.read_text(encoding="utf-8").splitlines()
        except FileNotFoundError:
            return []
        except OSError as exc:
            raise StoreError(f"{path}: cannot read the repair log ({os_error_text(exc)})") from None
        out = []
        for line in lines:
            try:
                out.append(Repair(**json.loads(line)))
            except (ValueError, TypeError):
                continue
        return out

    def verify(self, ref: ArtifactRef) -> bool:
        """True if the artifact is present and intact.

        A present file whose digest does not match is quarantined (see the
        module docstring) and False is returned, so the caller recomputes
        the stage that made it. A missing file gives False.
        """
        try:
            self.get_bytes(ref)
        except StoreError:  # missing, unreadable or corrupted (then quarantined)
            return False
        return True

    # -- raw bytes ---------------------------------------------------------
    @staticmethod
    def digest_of(data: bytes, *, kind: str, metadata: dict[str, Any]) -> str:
        """Digest of an artifact: SHA-256 of kind, canonical metadata and bytes."""
        h = hashlib.sha256(_DIGEST_PREFIX)
        h.update(canonical_dumps({"kind": kind, "metadata": metadata}).encode())
        h.update(b"\0")
        h.update(data)
        return h.hexdigest()

    def put_bytes(
        self, data: bytes, *, kind: str, suffix: str, metadata: dict[str, Any] | None = None
    ) -> ArtifactRef:
        """Store bytes (atomically) and return their reference.

        Raises :class:`StoreError` (one line naming the file) when the
        object cannot be written (a full disk, a read-only mount).

        An object that already exists with exactly these bytes is left
        alone; one with other bytes (a corrupted copy, even of the same size)
        is rewritten and the repair recorded (:attr:`repairs`).
        """
        meta = json.loads(canonical_dumps(metadata or {}))
        digest = self.digest_of(data, kind=kind, metadata=meta)
        relpath = object_relpath(digest, suffix)
        check_object_relpath(relpath, digest)  # a suffix the references refuse: before writing
        existing = self._existing_bytes(relpath)
        if existing != data:
            self._write_object(relpath, data)
            if existing is not None:
                self._record(
                    Repair(
                        relpath=relpath,
                        action="rewritten",
                        detail=f"{relpath}: existing content did not match its digest; rewritten",
                        time_utc=utc_now(),
                    )
                )
        return ArtifactRef(kind=kind, digest=digest, relpath=relpath, metadata=meta)

    def path(self, ref: ArtifactRef) -> Path:
        """Absolute path of an artifact's file."""
        return self.root / ref.relpath

    def exists(self, ref: ArtifactRef) -> bool:
        """True if the artifact's file is present."""
        return self.path(ref).is_file()

    def get_bytes(self, ref: ArtifactRef, *, verify: bool = True) -> bytes:
        """Read an artifact's bytes, checking its digest unless ``verify`` is False.

        Raises
        ------
        StoreError
            If the file is missing or cannot be read.
        CorruptArtifactError
            If its content does not match the digest; the file has then
            been quarantined, so that recomputing the stage heals the store.
        """
        data = self._read_object(ref)
        if verify and self.digest_of(data, kind=ref.kind, metadata=ref.metadata) != ref.digest:
            repair = self._quarantine(
                ref.relpath, f"{ref.relpath}: content does not match its digest; quarantined"
            )
            where = repair.quarantined_to or "(already moved)"
            raise CorruptArtifactError(
                f"artifact {self.path(ref)} is corrupted (digest mismatch); moved to {where} so "
                "the stage that made it can recompute it",
                ref=ref,
                repair=repair,
            )
        return data

    # -- the file operations a back-end replaces ----------------------------
    def _existing_bytes(self, relpath: str) -> bytes | None:
        """The bytes already stored under ``relpath``, or None (absent or unreadable)."""
        path = self.root / relpath
        try:
            return path.read_bytes() if path.is_file() else None
        except OSError:
            return None

    def _write_object(self, relpath: str, data: bytes) -> None:
        """Write the object ``relpath`` whole; :class:`StoreError` (one line) if it cannot."""
        path = self.root / relpath
        try:
            # looked up here at each call: a test replaces it to fill the disk
            atomic_write_bytes(path, data)
        except OSError as exc:  # a full disk, a read-only mount, ...
            raise StoreError(f"{path}: cannot write the artifact ({os_error_text(exc)})") from None

    def _read_object(self, ref: ArtifactRef) -> bytes:
        """The stored bytes of ``ref``, unverified; :class:`StoreError` if missing or unreadable."""
        path = self.path(ref)
        try:
            return path.read_bytes()
        except FileNotFoundError:
            raise StoreError(f"artifact {ref.kind} {ref.digest[:12]} is missing: {path}") from None
        except OSError as exc:
            raise StoreError(f"{path}: cannot read the artifact ({exc.strerror or exc})") from None

    # -- typed helpers -----------------------------------------------------
    def put_volume(
        self,
        array_zyx: np.ndarray,
        affine: np.ndarray,
        *,
        kind: str = "image",
        dtype: str | None = None,
        extra: dict[str, Any] | None = None,
    ) -> ArtifactRef:
        """Store a ``(z, y, x)`` volume as NIfTI; ``affine`` maps ``(x, y, z, 1)`` to RAS."""
        arr = np.asarray(array_zyx)
        if arr.ndim != 3:
            raise ValueError(f"a volume must be 3-D (z, y, x), got shape {arr.shape}")
        dt = np.dtype(dtype or (np.uint8 if arr.dtype == bool else arr.dtype))
        data = nifti.encode_nifti(arr.transpose(2, 1, 0), affine, dtype=dt)
        meta = {
            "dtype": dt.name,
            "shape_zyx": list(arr.shape),
            "affine": _affine_list(affine),
            **(extra or {}),
        }
        ref = self.put_bytes(data, kind=kind, suffix=".nii.gz", metadata=meta)
        memo = products()
        if memo.max_bytes:  # kept as get_volume returns it: the stored type, masks as bool
            stored = np.array(arr, dtype=dt, order="C")  # a copy: the caller's array may change
            memo.put(ref.digest, (stored > 0 if kind == "mask" else stored, _stored_affine(affine)))
        return ref

    def get_volume(self, ref: ArtifactRef) -> tuple[np.ndarray, np.ndarray]:
        """Load a volume: ``(array (z, y, x), affine)``; masks come back as bool."""
        arr_xyz, affine = nifti.decode_nifti(self.get_bytes(ref))
        arr = np.asarray(arr_xyz).transpose(2, 1, 0)
        if ref.kind == "mask":
            arr = arr > 0
        return np.ascontiguousarray(arr), affine

    def load_volume(self, ref: ArtifactRef) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`get_volume` through the process's memo of decoded volumes; arrays read-only.

        A volume this process stored or read before comes from memory under
        its content digest (:mod:`tumor3d.storage.product_memo`), equal to
        what :meth:`get_volume` returns; otherwise the store is read (and its
        digest checked) and the result kept. For stage inputs and publishing,
        which never modify an input; :meth:`get_volume` always reads.
        """
        memo = products()
        hit = memo.get(ref.digest)
        if hit is not None:
            array, affine = hit
            return array, affine
        array, affine = self.get_volume(ref)
        array.flags.writeable = affine.flags.writeable = False  # memo or not, as a hit
        memo.put(ref.digest, (array, affine))
        return array, affine

    def put_scan(self, scan: Scan) -> ArtifactRef:
        """Store a `Scan`: its image as float32 NIfTI plus its geometry as metadata.

        Not its patient id: the artifact, its digest and every cache key built
        on it depend on the content alone (the same file under two ids is one
        artifact), and a cached result never carries an id that publishing
        could attach to another patient. The caller names the patient again
        on reading (:meth:`get_scan`).
        """
        grid = scan.source_grid
        extra = {
            "pixel_spacing_mm": list(scan.pixel_spacing_mm),
            "slice_step_mm": float(scan.slice_step_mm),
            "slice_thickness_mm": float(scan.slice_thickness_mm),
            "slice_gap_mm": None if scan.slice_gap_mm is None else float(scan.slice_gap_mm),
            "modality": scan.modality,
            "source": scan.source,
            "source_grid": {
                "shape": list(grid.shape),
                "affine": _affine_list(grid.affine),
                "axes": list(grid.axes),
            },
        }
        if any(grid.flips):  # only when present, so other scans keep their digests
            extra["source_grid"]["flips"] = list(grid.flips)
        if grid.xform_codes != (1, 1):  # likewise
            extra["source_grid"]["xform_codes"] = list(grid.xform_codes)
        if grid.qform is not None:  # likewise
            extra["source_grid"]["qform"] = _affine_list(grid.qform)
        if scan.skipped_files:  # only when present, so other scans keep their digests
            extra["skipped_files"] = list(scan.skipped_files)
        if not scan.orientation_stated:  # likewise
            extra["orientation_stated"] = False
        return self.put_volume(scan.image, scan.affine, kind="scan", dtype="float32", extra=extra)

    def get_scan(self, ref: ArtifactRef, *, patient_id: str) -> Scan:
        """Load a `Scan` stored by :meth:`put_scan`, as patient ``patient_id``."""
        image, affine = self.get_volume(ref)
        return scan_from_metadata(image, affine, ref.metadata, patient_id=patient_id)

    def put_mesh(self, mesh: Mesh, *, extra: dict[str, Any] | None = None) -> ArtifactRef:
        """Store a mesh as binary PLY (RAS mm)."""
        meta = {"n_vertices": mesh.n_vertices, "n_faces": mesh.n_faces, **(extra or {})}
        return self.put_bytes(formats.encode_ply(mesh), kind="mesh", suffix=".ply", metadata=meta)

    def get_mesh(self, ref: ArtifactRef) -> Mesh:
        """Load a mesh."""
        return formats.decode_ply(self.get_bytes(ref), name=str(self.path(ref)))

    def put_table(self, table: pd.DataFrame | list[dict[str, Any]]) -> ArtifactRef:
        """Store a table as parquet."""
        df = table if isinstance(table, pd.DataFrame) else pd.DataFrame(table)
        meta = {"columns": [str(c) for c in df.columns], "n_rows": len(df)}
        return self.put_bytes(
            formats.encode_parquet(df), kind="table", suffix=".parquet", metadata=meta
        )

    def get_table(self, ref: ArtifactRef) -> pd.DataFrame:
        """Load a table."""
        return formats.decode_parquet(self.get_bytes(ref))

    def put_png(self, rgb: np.ndarray, *, extra: dict[str, Any] | None = None) -> ArtifactRef:
        """Store an RGB image as PNG."""
        meta = {"shape": list(np.shape(rgb)), **(extra or {})}
        return self.put_bytes(formats.encode_png(rgb), kind="png", suffix=".png", metadata=meta)

    def put_json(self, obj: Any) -> ArtifactRef:
        """Store a small JSON document."""
        return self.put_bytes(canonical_dumps(obj).encode(), kind="json", suffix=".json")

    def get_json(self, ref: ArtifactRef) -> Any:
        """Load a JSON document."""
        return json.loads(self.get_bytes(ref))


def scan_from_metadata(
    image: np.ndarray, affine: np.ndarray, meta: dict[str, Any], *, patient_id: str
) -> Scan:
    """Rebuild a `Scan` from its image, affine and stored metadata, as patient ``patient_id``."""
    return Scan(
        image=image,
        affine=affine,
        pixel_spacing_mm=tuple(meta["pixel_spacing_mm"]),
        slice_step_mm=meta["slice_step_mm"],
        slice_thickness_mm=meta["slice_thickness_mm"],
        slice_gap_mm=meta["slice_gap_mm"],
        modality=meta["modality"],
        patient_id=patient_id,
        source=meta["source"],
        source_grid=source_grid_from_metadata(meta),
        skipped_files=tuple(meta.get("skipped_files", ())),
        orientation_stated=bool(meta.get("orientation_stated", True)),
    )


def source_grid_from_metadata(meta: dict[str, Any]) -> SourceGrid:
    """The `SourceGrid` recorded in a scan artifact's metadata."""
    sg = meta["source_grid"]
    return SourceGrid(
        shape=tuple(sg["shape"]),
        affine=np.asarray(sg["affine"]),
        axes=tuple(sg["axes"]),
        flips=tuple(bool(f) for f in sg.get("flips", (False, False, False))),
        xform_codes=tuple(int(c) for c in sg.get("xform_codes", (1, 1))),
        qform=None if sg.get("qform") is None else np.asarray(sg["qform"]),
    )
