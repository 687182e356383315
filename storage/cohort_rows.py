"""The checks of a cohort's manifest rows before any work (:func:`validate_rows`).

Every row needs a ``patient_id`` and an ``image``; the ids give distinct output
folders (BIDS participant labels with ``layout="bids"``); no row's output folder
holds an input of that row or of any other (:mod:`tumor3d.storage.publish`), nor
does a BIDS dataset root. :func:`tumor3d.flows.cohort.run_cohort` and the command
line (:func:`tumor3d.flows.cohort.check_cohort_rows`) run them first.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from tumor3d.errors import InputError
from tumor3d.storage import bids
from tumor3d.storage.publish import check_destination, check_outputs_not_inputs

__all__ = ["validate_rows"]

#: A row's columns naming input files (never inside any row's output folder).
_INPUT_COLUMNS = ("image", "brain_mask", "segmentation")


def validate_rows(
    rows: list[dict[str, Any]], out_dir: Path | None, layout: str = "default"
) -> None:
    """Refuse a cohort's rows before any work: one line naming the first bad row.

    Parameters
    ----------
    rows : list of dict
        Manifest rows as plain dicts (``patient_id``, ``image``, optional
        ``brain_mask`` and ``segmentation``; other keys ignored).
    out_dir : Path or None
        The local output folder ``DIR``; None for an object-store URL (the inputs
        are local files, so it cannot hold one).
    layout : {"default", "bids"}
        ``"bids"``: folders are ``sub-<label>`` (:mod:`tumor3d.storage.bids`); only
        a local ``DIR``.

    Raises
    ------
    InputError
        A row without ``patient_id`` or ``image``, an id that is no valid folder
        (or BIDS label), two rows with one folder, an output folder over an input,
        or ``layout="bids"`` with an object-store output.
    """
    seen: dict[str, tuple[str, int]] = {}  # folder -> (its patient id, its row)
    for i, row in enumerate(rows, start=1):
        pid = row.get("patient_id")
        if not pid or "image" not in row:
            raise InputError(f"manifest row {i}: needs patient_id and image")
        try:
            folder = bids.folder_name(str(pid), layout)
        except InputError as exc:
            raise InputError(f"manifest row {i}: {exc}") from None
        if folder in seen:
            first, j = seen[folder]
            if first == str(pid):
                raise InputError(f"manifest row {i}: duplicate patient_id {pid!r} (row {j})")
            raise InputError(  # the BIDS layout folds two ids onto one participant label
                f"manifest row {i}: patient_id {pid!r} and {first!r} (row {j}) would both "
                f"publish into {folder}"
            )
        seen[folder] = (str(pid), i)
        # never publish over an input (checked for every row before any work); inputs
        # are local files, so an object-store output (out_dir None) cannot hold one
        if out_dir is not None:
            given = [row[k] for k in _INPUT_COLUMNS if row.get(k)]
            check_destination(out_dir / folder, given)
    if out_dir is not None:  # nor over another row's input (a mask kept in its folder)
        inputs = [r[k] for r in rows for k in _INPUT_COLUMNS if r.get(k)]
        check_outputs_not_inputs([out_dir / f for f in seen], inputs)
        if layout == "bids":  # OUT/dataset_description.json: absent or ours, never an input
            bids.check_dataset_root(out_dir, inputs)
    elif layout == "bids":
        raise InputError("--layout bids writes a local folder: give a local --out")
