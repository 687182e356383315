"""The cohort's outputs: ``cohort.parquet`` (one row per patient), ``cohort.md`` and ``.html``.

``cohort.html`` (:func:`cohort_page_rows` + :func:`tumor3d.storage.report_html.cohort_report_html`)
sits beside ``cohort.parquet``: one row per patient with its anterior render
as thumbnail, its volumes, its status (``ok``, ``check`` or ``failed``:
:mod:`tumor3d.segmentation.review`; the failing stage and error of a failed patient), its
notes (why to check first) and a link to its ``report.html``, and a
distribution plot of the Eq. 7 volumes. Links are relative (``<patient_id>/report.html``) and made
only to files that exist, and never to a failed patient's folder (which may
hold an earlier run's results), so the cohort folder can be moved as a whole.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import pandas as pd

from tumor3d.segmentation.review import STATUS_CHECK, STATUS_FAILED, STATUS_OK
from tumor3d.storage.atomic import atomic_write_bytes
from tumor3d.storage.formats import encode_parquet
from tumor3d.storage.objectstore import is_url
from tumor3d.storage.patient_outputs import split_notes
from tumor3d.storage.provenance import patients_by_reason
from tumor3d.storage.report_html import cohort_report_html

__all__ = [
    "cohort_markdown",
    "cohort_title",
    "row_notes",
    "cohort_output_files",
    "cohort_page_rows",
    "cohort_table",
    "published_patient_ids",
    "write_cohort_outputs",
]

_FIRST = ("patient_id", "status", "failed_stage", "error", "output_dir", "recomputed")


def cohort_table(
    outcomes: Sequence[Mapping[str, Any]], out_dir: str | Path | None = None
) -> pd.DataFrame:
    """One row per patient: id, status, failing stage, error, then every metrics column.

    Parameters
    ----------
    outcomes : sequence of mapping
        Each with ``patient_id``, ``status``, ``failed_stage``, ``error``,
        ``output_dir`` and ``metrics`` (that patient's ``metrics.parquet`` row,
        empty when it failed).
    out_dir : str or path, optional
        The cohort's folder or URL: ``output_dir`` is then written relative to it
        (``p1``, ``sub-p1``), so the table resolves wherever the folder is read or
        moved to; it was relative to the working folder of the command.

    Examples
    --------
    >>> t = cohort_table([{"patient_id": "p1", "status": "ok", "output_dir": "runs/out/p1"}],
    ...                  out_dir="runs/out")
    >>> t.loc[0, "output_dir"]
    'p1'
    """
    rows = []
    for o in outcomes:
        row = {k: o.get(k) for k in _FIRST}
        row["output_dir"] = _relative_to(row["output_dir"], out_dir)
        row.update({k: v for k, v in dict(o.get("metrics") or {}).items() if k != "patient_id"})
        rows.append(row)
    table = pd.DataFrame(rows, columns=None)
    for col in _FIRST:
        if col not in table.columns:
            table[col] = None
        table[col] = table[col].astype(object)
    return table[[*_FIRST, *[c for c in table.columns if c not in _FIRST]]]


def _relative_to(folder: Any, base: str | Path | None) -> Any:
    """``folder`` relative to ``base`` when it lies in it (a path or a URL), else as given."""
    if base is None or not isinstance(folder, str) or not folder:
        return folder
    if is_url(base):  # an object store's URL
        prefix = str(base).rstrip("/") + "/"
        return folder[len(prefix) :] if folder.startswith(prefix) else folder
    rel = os.path.relpath(folder, base)
    return folder if rel == ".." or rel.startswith("../") else rel


def cohort_title(name: str | None) -> str:
    """The cohort pages' title: ``tumor3d cohort: <name>`` (no name twice).

    >>> cohort_title("cohort"), cohort_title("brats-2013"), cohort_title("")
    ('tumor3d cohort', 'tumor3d cohort: brats-2013', 'tumor3d cohort')
    """
    name = (name or "").strip()
    return "tumor3d cohort" if name.lower() in ("", "cohort") else f"tumor3d cohort: {name}"


def row_notes(row: Mapping[str, Any]) -> list[str]:
    """A cohort row's notes: why to check it first, then its other notes (no repeats)."""
    out = split_notes(row.get("review_reasons"))
    return out + [n for n in split_notes(row.get("notes")) if n not in out]


def _fmt(value: Any, spec: str) -> str:
    try:
        return format(float(value), spec)
    except (TypeError, ValueError):
        return "-"


def _eq7_slices(row: Any) -> str:
    """The slices Eq. 7 summed and its rule: ``31 (segmented)``; ``-`` when unknown.

    >>> _eq7_slices({"n_eq7_slices": 12, "eq7_slice_rule": "segmented"})
    '12 (segmented)'
    """
    n, rule = row.get("n_eq7_slices"), row.get("eq7_slice_rule")
    count = _fmt(n, ".0f")
    return count if not rule or not isinstance(rule, str) else f"{count} ({rule})"


def cohort_markdown(
    table: pd.DataFrame,
    *,
    volume_labels: Mapping[str, str],
    stage_names: Sequence[str],
    title: str,
    wall_seconds: float,
    workers: int,
    removed: Sequence[str] = (),
    earlier: Sequence[str] = (),
) -> str:
    """A Markdown summary: status, volumes (mm3 and mL) per method and notes, failures, stages.

    ``earlier``: failed patients whose folder still holds an earlier run's result,
    said under the failures.

    Every patient that completed is in the volume table, with its status
    (``ok`` or ``check``) and notes (why to check first).

    ``removed`` names patients published in the output folder by an earlier
    run but no longer in the manifest: listed in a section of their own (their
    folders are kept, never deleted).
    """
    failed = table[table["status"] == STATUS_FAILED]
    ok = table[table["status"] != STATUS_FAILED]  # completed: ok or check
    n_check = int((table["status"] == STATUS_CHECK).sum())
    n_ok = int((table["status"] == STATUS_OK).sum())
    lines = [
        f"# {title}",
        "",
        f"{len(table)} patients: {n_ok} ok, {n_check} to check, {len(failed)} failed; wall "
        f"time {wall_seconds:.1f} s with {workers} worker(s).",
        "",
        "Status: **ok** -- completed and nothing asks for a human; **check** -- completed, "
        "but the tool's own checks doubt the result (the notes say why: look before using "
        "it); **failed** -- did not complete.",
        "",
        "## Volumes",
        "",
        "| patient | status | modality | "
        + " | ".join(f"{volume_labels[k]} (mm3) | (mL)" for k in volume_labels)
        + " | Eq. 7 slices (rule) | notes |",
        "|---|---|---|" + "---:|---:|" * len(volume_labels) + "---:|---|",
    ]
    for _, r in ok.iterrows():
        cells = []
        for k in volume_labels:
            cells += [_fmt(r.get(k), ",.1f"), _fmt(r.get(k.replace("_mm3", "_ml")), ".3f")]
        notes = "; ".join(row_notes(r)).replace("|", "\\|")
        status = f"**{r['status']}**" if r["status"] == STATUS_CHECK else str(r["status"])
        lines.append(
            f"| {r['patient_id']} | {status} | {r.get('modality') or '-'} | "
            + " | ".join(cells)
            + f" | {_eq7_slices(r)} | {notes} |"
        )
    lines += ["", "## Failures", ""]
    if failed.empty:
        lines.append("None.")
    else:
        lines += ["| patient | failing stage | error |", "|---|---|---|"]
        for _, r in failed.iterrows():
            error = str(r["error"]).replace("|", "\\|")
            lines.append(f"| {r['patient_id']} | {r['failed_stage']} | {error} |")
        if earlier:
            lines += ["", f"The folder of {', '.join(earlier)} {EARLIER_NOTE}."]
    # published before, and this result is not that one: why
    again = (
        patients_by_reason(zip(table["patient_id"], table["recomputed"], strict=True))
        if "recomputed" in table.columns
        else {}
    )
    if again:
        lines += ["", "## Since the earlier result", ""]
        lines += [f"- {why}: {', '.join(ids)}" for why, ids in again.items()]
    if removed:
        lines += [
            "",
            "## Removed from the manifest",
            "",
            f"{len(removed)} patient(s) published by an earlier run are no longer in the "
            "manifest; their folders are kept (not deleted): " + ", ".join(removed) + ".",
        ]
    lines += [
        "",
        "## Stages",
        "",
        "Compute time of the stages that ran (cache hits keep the time of the run that "
        "computed them), over the patients that succeeded.",
        "",
        "| stage | total compute (s) | mean (s) | cache hits |",
        "|---|---:|---:|---:|",
    ]
    for stage in stage_names:
        key = stage.replace("-", "_")
        t, c = f"time_{key}_s", f"cached_{key}"
        if t not in ok.columns:
            continue
        hits = int(ok[c].astype(bool).sum()) if c in ok.columns else 0
        lines.append(f"| {stage} | {ok[t].sum():.2f} | {ok[t].mean():.2f} | {hits}/{len(ok)} |")
    return "\n".join(lines) + "\n"


def _finite(value: Any) -> float | None:
    try:
        f = float(value)
    except (TypeError, ValueError):
        return None
    return f if f == f and abs(f) != float("inf") else None


#: Said of a failed patient whose folder holds an earlier run's result (cohort.md, .html).
EARLIER_NOTE = (
    "still holds an earlier run's result, not this run's input's (this run failed before "
    "publishing): do not read it as this run's"
)


def cohort_page_rows(
    table: pd.DataFrame,
    out_dir: str | Path,
    *,
    exists: Callable[[str], bool] | None = None,
    earlier: Sequence[str] = (),
) -> list[dict[str, Any]]:
    """The rows of ``cohort.html``: per patient its status, volumes, notes and relative links.

    Parameters
    ----------
    table : DataFrame
        :func:`cohort_table`'s table.
    out_dir : path
        The cohort folder (``cohort.html``'s folder); links are relative to it
        and made only to files that exist there.
    exists : callable, optional
        ``exists("<patient_id>/<file>")``: whether that file is published (for
        an object store); default: the file exists under ``out_dir``.
    earlier : sequence of str
        Failed patients whose folder still holds an earlier run's result: their row
        says so, as ``cohort.md`` does (:func:`cohort_markdown`).
    """
    out = Path(out_dir)
    if exists is None:
        exists = lambda rel: (out / rel).is_file()  # noqa: E731
    rows = []
    for r in table.to_dict(orient="records"):
        pid = str(r["patient_id"])
        ok = r.get("status") != STATUS_FAILED  # completed: ok or check
        if ok:
            status = str(r.get("status") or STATUS_OK)
        else:
            status = f"failed at {r.get('failed_stage') or '?'}: {r.get('error') or ''}".strip()
        vols = {
            key: _finite(r.get(f"volume_{key}_mm3"))
            for key in ("eq7", "voxel", "mesh", "mesh_simplified")
            if f"volume_{key}_mm3" in r
        }
        row: dict[str, Any] = {"patient_id": pid, "status": status}
        if not ok and pid in earlier:
            row["notes"] = [f"its folder {EARLIER_NOTE}"]
        if ok:
            row["notes"] = row_notes(r)
            row["volumes_mm3"] = vols
            # the folder published (sub-<label> in the BIDS layout), else the id
            done = r.get("output_dir")
            folder = Path(str(done)).name if isinstance(done, str) and done else pid
            for thumb in (
                f"{folder}/render_anterior.png",
                f"{folder}/figures/{folder}_desc-anterior_render.png",  # tumor3d.storage.bids
            ):
                if exists(thumb):
                    row["thumbnail"] = thumb
                    break
            if exists(f"{folder}/report.html"):
                row["report"] = f"{folder}/report.html"
        rows.append(row)
    return rows


def published_patient_ids(out_dir: str | Path) -> list[str]:
    """Patients already published in ``out_dir``: sub-folders holding ``metrics.parquet``, sorted.

    Hidden folders (staging, trash, the artifact store) are not patients.
    """
    out = Path(out_dir)
    if not out.is_dir():
        return []
    return sorted(
        p.name
        for p in out.iterdir()
        if not p.name.startswith(".") and p.is_dir() and (p / "metrics.parquet").is_file()
    )


def cohort_output_files(
    table: pd.DataFrame,
    markdown: str,
    out_dir: str | Path,
    *,
    name: str | None = None,
    exists: Callable[[str], bool] | None = None,
    removed: Sequence[str] = (),
    earlier: Sequence[str] = (),
) -> dict[str, bytes]:
    """The bytes of ``cohort.parquet``, ``cohort.md`` and ``cohort.html`` (file name -> bytes).

    ``name`` is the cohort's name in the page title (:func:`cohort_title`;
    default ``out_dir``'s name); ``exists`` and ``earlier`` as :func:`cohort_page_rows`;
    ``removed`` as :func:`cohort_markdown` (the page lists them too).
    """
    title = cohort_title(name if name is not None else Path(out_dir).name)
    rows = cohort_page_rows(table, out_dir, exists=exists, earlier=earlier)
    page = cohort_report_html(rows, title=title, removed=removed)
    return {
        "cohort.parquet": encode_parquet(table),
        "cohort.md": markdown.encode(),
        "cohort.html": page.encode("utf-8"),
    }


def write_cohort_outputs(
    out_dir: str | Path,
    table: pd.DataFrame,
    markdown: str,
    removed: Sequence[str] = (),
    earlier: Sequence[str] = (),
) -> None:
    """Write ``cohort.parquet``, ``cohort.md`` and ``cohort.html`` atomically into ``out_dir``."""
    out = Path(out_dir)
    files = cohort_output_files(table, markdown, out, removed=removed, earlier=earlier)
    for fname, data in files.items():
        atomic_write_bytes(out / fname, data)
