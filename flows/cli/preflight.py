"""Checks before a run starts: the input, the output folder, the given masks, the modality."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from rich.markup import escape

from tumor3d.flows.cli.app import console


def _location(where: str | Path) -> str | Path:
    """An ``s3://`` URL as given (a Path would fold its ``//``), else a local path."""
    from tumor3d.storage.objectstore import is_url

    return str(where) if is_url(where) else Path(where)


def _preflight(
    input_path: Path,
    out: str | Path,
    options: Any,
    store: str | Path | None = None,
    brain_mask: Path | None = None,
    segmentation: Path | None = None,
    layout: str = "default",
) -> None:
    """Check the destination, read the input and open the store before starting Prefect.

    ``options``: the run's :class:`~tumor3d.storage.readers.options.ReadOptions`.
    The scan read here is handed to the ingest stage, which does not read the
    input again (:mod:`tumor3d.storage.readers.handoff`).

    Bad input then fails in a second, an output folder that is or holds the
    input (or the brain mask), holds files other than a tumor3d result, or
    (for a patient id derived from the file name) holds another input's
    results is refused before any work, a given brain mask
    is checked against the image (grid, values, overlap), a given
    segmentation against its grid and values, and a store that
    is a file or cannot be created is named before a temporary server is
    started for nothing. An ``s3://`` output or store is reached (one line
    naming the URL if it cannot be) instead, never made a local folder.
    """
    from tumor3d.errors import InputError
    from tumor3d.storage import bids
    from tumor3d.storage.inputs import input_digest, input_location
    from tumor3d.storage.publish import check_destination
    from tumor3d.storage.readers import derive_patient_id, suggest_patient_id
    from tumor3d.storage.readers.handoff import read_and_keep

    out = _location(out)
    if bids.check_layout(layout) == "bids" and isinstance(out, str):
        raise InputError("--layout bids writes a local folder: give a local --out", path=out)
    if isinstance(out, str):
        _preflight_remote(input_path, out, options, store, brain_mask, segmentation)
        return
    _check_out_dir(out)
    patient_id = options.patient_id  # checked by ReadOptions
    if input_path.exists():
        pid = patient_id if patient_id else derive_patient_id(input_path)
        given = [input_path] + [m for m in (brain_mask, segmentation) if m is not None]
        if layout == "bids":  # a BIDS participant label; OUT's description absent or ours
            bids.check_dataset_root(out, given)
        # the content is hashed only if a record of another location is there to compare
        check_destination(
            out / bids.folder_name(pid, layout), given,
            derived_from=None if patient_id else (lambda: input_digest(input_path)),
            location=input_location(input_path), suggestion=suggest_patient_id(input_path),
        )  # fmt: skip
    scan = read_and_keep(input_path, options)  # the ingest stage takes it: one read
    _check_given_masks(scan, brain_mask, segmentation, options.max_voxels)
    from tumor3d.flows.api_use import check_configured_api

    check_configured_api()  # an unreachable PREFECT_API_URL: one line, nothing created
    _reach_destinations(out, store, make_local_store=True)
    _check_out_writable(out)


def _check_out_writable(out: Path) -> None:
    """A local output folder that cannot be written is named before any work (exit 3).

    With ``--store`` elsewhere nothing else writes there before publishing: an
    immutable or read-only folder failed after every stage had run.
    """
    from tumor3d.storage.atomic import check_writable_dir

    check_writable_dir(out, create=False)  # made when the run starts, not by a refused one


def _preflight_remote(
    input_path: Path,
    out: str,
    options: Any,
    store: str | Path | None = None,
    brain_mask: Path | None = None,
    segmentation: Path | None = None,
) -> None:
    """:func:`_preflight` for an ``s3://`` output: inputs are local, so none can lie in it."""
    from tumor3d.storage.readers.handoff import read_and_keep

    scan = read_and_keep(input_path, options)  # the ingest stage takes it: one read
    _check_given_masks(scan, brain_mask, segmentation, options.max_voxels)
    from tumor3d.flows.api_use import check_configured_api

    check_configured_api()  # an unreachable PREFECT_API_URL: one line, nothing created
    _reach_destinations(out, store, make_local_store=True)


def _reach_destinations(
    out: str | Path, store: str | Path | None, *, make_local_store: bool
) -> None:
    """Reach an ``s3://`` output and store (one line naming the URL if one cannot be).

    The store is ``store``, else the output's default; a local one is created when
    ``make_local_store`` (a file in its place or an unwritable parent is named).
    """
    from tumor3d.storage.objectstore import default_store_location, is_url, open_store

    if is_url(out):
        from tumor3d.storage.remote_publish import RemoteFolder

        RemoteFolder(str(out)).check()
    at = store if store is not None else default_store_location(out)
    if is_url(at):
        open_store(str(at)).check()  # type: ignore[attr-defined]
    elif make_local_store:
        from tumor3d.storage.store import ArtifactStore

        ArtifactStore(at)


def _preflight_cohort(out: str | Path, store: str | Path | None, dask_address: str | None) -> None:
    """Reach a cohort's ``s3://`` output and store and its Dask workers before starting Prefect.

    :func:`tumor3d.flows.cohort.run_cohort` checks them again (a second round trip
    when they answer) and creates a local store; here an unreachable one is named in
    one line before a temporary Prefect server is started for nothing.
    """
    _reach_destinations(out, store, make_local_store=False)
    if dask_address:
        from tumor3d.flows.dask_runner import check_scheduler
        from tumor3d.flows.dask_workers import check_workers
        from tumor3d.storage.objectstore import default_store_location

        check_scheduler(dask_address)
        check_workers(dask_address, store if store is not None else default_store_location(out))


def _check_given_masks(
    scan: Any, brain_mask: Path | None, segmentation: Path | None, limit: int
) -> None:
    """A given brain mask and segmentation checked against the image (one line naming the file)."""
    if brain_mask is not None:
        from tumor3d.storage.brain_mask import read_given_brain_mask

        read_given_brain_mask(brain_mask, scan, max_voxels=limit)
    if segmentation is not None:
        from tumor3d.storage.given_segmentation import read_given_segmentation

        read_given_segmentation(segmentation, scan, max_voxels=limit)


def _say_modality(modality: str, origin: str, input_path: Path | None = None) -> None:
    """Say the modality the run used, and where it came from when not from --modality.

    ``origin``: as :func:`tumor3d.storage.readers.resolve_modality` gives it. A given one
    that overrides another named by the input's stack sidecar says both (a user audit:
    a typo in --modality passed silently over the sidecar's).
    """
    if origin == "given":
        from tumor3d.errors import InputError
        from tumor3d.storage.readers import declared_modality

        try:  # an unreadable sidecar was not needed: the option decided
            declared = None if input_path is None else declared_modality(input_path)
        except InputError:
            declared = None
        said = f"modality: {escape(modality)}"
        if declared is not None and declared != modality:
            said += f" (given; the stack's sidecar names {escape(declared)})"
        console.print(said, highlight=False)
    elif origin == "input":
        said = f"modality: {escape(modality)} (named by the stack's sidecar)"
        console.print(said, highlight=False)
    else:
        console.print(
            f"modality: [bold]{escape(modality)}[/] (the default: --modality was not given; it "
            "decides the segmentation, so give --modality flair or t1c for those images)",
            highlight=False, soft_wrap=True,
        )  # fmt: skip


def _say_derived_id(input_path: Path) -> None:
    """Say the patient id made from the input's name when making it folder-safe changed it."""
    from tumor3d.storage.readers.common import derive_patient_id, id_source_name

    name, pid = id_source_name(input_path), derive_patient_id(input_path)
    if pid != name:
        console.print(
            f"patient id: {escape(pid)} (made folder-safe from the name {escape(repr(name))}; "
            "--patient-id gives your own)",
            highlight=False, soft_wrap=True,
        )  # fmt: skip


def _check_out_dir(out: Path) -> None:
    """An output folder that exists as a file is bad input (exit 2), found before any work."""
    from tumor3d.errors import InputError

    if out.exists() and not out.is_dir():
        raise InputError("the output folder (--out) is a file, not a folder", str(out))
