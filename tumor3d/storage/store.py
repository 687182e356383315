"""Content-addressed artifact store.

Each artifact is a file under ``<root>/objects/<d[:2]>/<d>.<suffix>`` where
``d`` is the SHA-256 digest of the artifact's kind, its canonical metadata
(dtype, shape, spacing and affine for images) and its bytes. Files are
written under a temporary name in the same folder, flushed and renamed, so a
crash never leaves a half-written artifact under its final name. Nothing is
ever unpickled: images are NIfTI, meshes PLY, tables parquet, renders PNG,
small records JSON.

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

import errno
import hashlib
import json
import os
import re
import socket
import tempfile
import time
import uuid
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from pydantic import BaseModel, ConfigDict, Field

from tumor3d.errors import InputError, Tumor3DError, os_error_path, os_error_text
from tumor3d.geometry.mesh import Mesh
from tumor3d.imaging.scan import Scan, SourceGrid
from tumor3d.storage import formats, nifti
from tumor3d.storage.product_memo import products

__all__ = [
    "ArtifactRef",
    "ArtifactStore",
    "CorruptArtifactError",
    "Repair",
    "StoreError",
    "atomic_write_bytes",
    "canonical_dumps",
    "check_writable_dir",
    "process_alive",
    "utc_now",
    "writer_gone",
]

_DIGEST_PREFIX = b"tumor3d-artifact-v1\0"


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
        by :meth:`ArtifactStore.put_bytes`).
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
        Path of the file relative to the store root.
    metadata : dict
        Canonical, JSON-able description (shape, dtype, affine, ...).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: str
    digest: str = Field(pattern=r"^[0-9a-f]{64}$")
    relpath: str
    metadata: dict[str, Any] = Field(default_factory=dict)


def canonical_dumps(obj: Any) -> str:
    """JSON with sorted keys and no whitespace; NaN is refused."""
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False)


def _host_identity() -> str:
    """Who can ask this process's pids: the host name, this boot and the pid namespace.

    Two machines of one name differ by their boot, two containers of one name by
    their pid namespace; Linux's ``/proc`` gives those two, elsewhere the host name
    alone.
    """
    parts = [socket.gethostname()]
    try:
        parts.append(Path("/proc/sys/kernel/random/boot_id").read_text().strip())
        parts.append(str(os.stat("/proc/self/ns/pid").st_ino))
    except OSError:
        pass
    return "\0".join(parts)


#: This machine and pid namespace, in temporary file names: 8 hex digits of
#: :func:`_host_identity`'s SHA-256. A writer of the same tag can be asked by pid.
HOST_TAG = hashlib.sha256(_host_identity().encode()).hexdigest()[:8]

#: A temporary file or upload whose writer cannot be asked (another machine's, an
#: object store's) untouched for this long is a killed writer's (seconds; a write
#: takes seconds).
STALE_TMP_S = 3600.0

#: ``.<name>.tmp-<host tag>-<pid>-<random>``, the temporary name of
#: :func:`atomic_write_bytes` (``.<name>.tmp-<pid>-<random>`` before the host tag).
_TMP_NAME = re.compile(r"^\.(?P<name>.+)\.tmp-(?:(?P<host>[0-9a-f]{8})-)?(?P<pid>\d+)-[0-9a-f]{8}$")


def process_alive(pid: int) -> bool:
    """True if process ``pid`` of this machine exists (ours, or another user's)."""
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's live process
        return True
    return True


def writer_gone(
    host: str | None, pid: int, path: Path, *, now: float, max_age_s: float = STALE_TMP_S
) -> bool:
    """Whether a temporary file or folder, named with its writer's host tag and pid, is left.

    Left by a writer that is gone: this machine's and pid namespace's
    (:data:`HOST_TAG`) when its process no longer exists; any when ``path`` is
    untouched for ``max_age_s`` (another machine's, whose pids cannot be asked
    here, or one whose pid was since reused). Raises ``OSError`` when ``path``
    cannot be examined (the caller leaves it).
    """
    if host == HOST_TAG and not process_alive(pid):
        return True
    return now - Path(path).stat().st_mtime > max_age_s


def atomic_write_bytes(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename.

    The temporary file lives in the destination folder (same file system),
    is fsynced, then atomically renamed over ``path``. Its name,
    ``.<name>.tmp-<host tag>-<pid>-<random>``, says which process wrote it,
    so that one left by a killed process can be told from one being written
    (:meth:`ArtifactStore.clean_stale_tmp`).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{HOST_TAG}-{os.getpid()}-{uuid.uuid4().hex[:8]}")
    try:
        with open(tmp, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def check_writable_dir(folder: Path, *, create: bool = True) -> None:
    """Check that a file can be created in ``folder``, made with its parents if ``create``.

    Called before any work by the commands and flows that write results there, so
    an immutable or read-only output folder is named at once instead of after every
    stage has run. Without ``create`` (a check before the input is validated: a
    refused command leaves nothing behind) an absent folder is judged by its
    nearest existing parent, where it would be made.

    Raises
    ------
    OSError
        Naming ``folder`` (not the probe's random name): it cannot be made or written.
    """
    folder = Path(folder)
    where = folder
    if not create:
        while not where.exists() and where.parent != where:
            where = where.parent
        if where.exists() and not where.is_dir():
            raise NotADirectoryError(errno.ENOTDIR, os.strerror(errno.ENOTDIR), str(where))
    try:
        if create:
            folder.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(prefix=".tumor3d-probe-", dir=where)
    except OSError as exc:
        raise OSError(exc.errno, exc.strerror, str(folder)) from None
    os.close(fd)
    os.unlink(probe)


def utc_now() -> str:
    """The time now in UTC, to the second, as the records write it (``2026-12-06T03:12:00Z``)."""
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def _affine_list(affine: np.ndarray) -> list[list[float]]:
    return [[float(v) for v in row] for row in np.asarray(affine, dtype=np.float64)]


def _stored_affine(affine: np.ndarray) -> np.ndarray:
    """The affine a stored volume reads back with: NIfTI keeps the sform as float32."""
    return np.asarray(affine, dtype=np.float64).astype(np.float32).astype(np.float64)


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

    def _quarantine(self, path: Path, detail: str) -> Repair:
        """Move a bad object aside (never delete it) so that it can be rewritten."""
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
        target = self.root / "quarantine" / f"{path.name}.{stamp}-{uuid.uuid4().hex[:8]}"
        target.parent.mkdir(parents=True, exist_ok=True)
        try:
            os.replace(path, target)
            moved: str | None = target.relative_to(self.root).as_posix()
        except FileNotFoundError:  # another process moved or rewrote it first
            moved = None
        return self._record(
            Repair(
                relpath=path.relative_to(self.root).as_posix(),
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
        removed: list[str] = []
        now = time.time()
        try:
            found = list((self.root / "objects").glob("*/.*.tmp-*"))
        except OSError:
            return removed
        for tmp in found:
            m = _TMP_NAME.match(tmp.name)
            if m is None:
                continue
            try:
                stale = writer_gone(m["host"], int(m["pid"]), tmp, now=now, max_age_s=max_age_s)
                if stale:
                    tmp.unlink()
            except OSError:  # renamed into place meanwhile, another user's, read-only
                continue
            if stale:
                removed.append(str(tmp))
        return removed

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
        relpath = f"objects/{digest[:2]}/{digest}{suffix}"
        path = self.root / relpath
        try:
            existing = path.read_bytes() if path.is_file() else None
        except OSError:
            existing = None
        if existing != data:
            try:
                atomic_write_bytes(path, data)
            except OSError as exc:  # a full disk, a read-only mount, ...
                raise StoreError(
                    f"{path}: cannot write the artifact ({os_error_text(exc)})"
                ) from None
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
        path = self.path(ref)
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            raise StoreError(f"artifact {ref.kind} {ref.digest[:12]} is missing: {path}") from None
        except OSError as exc:
            raise StoreError(f"{path}: cannot read the artifact ({exc.strerror or exc})") from None
        if verify and self.digest_of(data, kind=ref.kind, metadata=ref.metadata) != ref.digest:
            repair = self._quarantine(
                path, f"{ref.relpath}: content does not match its digest; quarantined"
            )
            where = repair.quarantined_to or "(already moved)"
            raise CorruptArtifactError(
                f"artifact {path} is corrupted (digest mismatch); moved to {where} so the "
                "stage that made it can recompute it",
                ref=ref,
                repair=repair,
            )
        return data

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
