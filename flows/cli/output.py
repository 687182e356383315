"""What the user sees: progress per stage, the patient's and the cohort's summaries."""

from __future__ import annotations

import sys
import threading
from pathlib import Path
from typing import Any

from rich import box
from rich.markup import escape
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn
from rich.table import Table

from tumor3d.flows.cli.app import console
from tumor3d.flows.cli.errors import EXIT_CHECK

#: Rich style of each status (tumor3d.segmentation.review).
_STATUS_STYLE = {"ok": "bold green", "check": "bold yellow", "failed": "bold red"}


def _slices_inserted(n: int) -> str:
    """``1 slice inserted`` / ``4 slices inserted``.

    >>> _slices_inserted(1), _slices_inserted(0)
    ('1 slice inserted', '0 slices inserted')
    """
    return f"{n} slice{'' if n == 1 else 's'} inserted"


def _status_text(status: str) -> str:
    return f"[{_STATUS_STYLE.get(status, 'bold')}]{escape(status)}[/]"


class _ProgressReporter:
    """Shows one progress bar per patient, advancing stage by stage."""

    def __init__(self, progress: Progress) -> None:
        self.progress = progress
        self.bars: dict[str, Any] = {}

    def __call__(self, event: Any) -> None:
        pid = escape(event.patient_id)
        bar = self.bars.get(event.patient_id)
        if bar is None:
            bar = self.progress.add_task(pid, total=event.total)
            self.bars[event.patient_id] = bar
        if event.status == "started":
            self.progress.update(bar, description=f"{pid}: {event.stage}")
        elif event.status in ("done", "cached"):
            note = "cached" if event.status == "cached" else f"{event.seconds:.1f} s"
            self.progress.update(
                bar, completed=event.index, description=f"{pid}: {event.stage} ({note})"
            )


class _CohortReporter:
    """One bar over patients; its description shows the current stage of each active one."""

    def __init__(self, progress: Progress, n_patients: int) -> None:
        self.progress = progress
        self.bar = progress.add_task("patients", total=n_patients)
        self.current: dict[str, str] = {}
        self.failed = 0

    def __call__(self, event: Any) -> None:
        if event.status in ("published", "failed"):
            self.current.pop(event.patient_id, None)
            self.failed += event.status == "failed"
            self.progress.advance(self.bar)
        elif event.status == "started":
            self.current[event.patient_id] = event.stage
        active = ", ".join(f"{escape(p)}: {s}" for p, s in sorted(self.current.items()))
        failed = f" ({self.failed} failed)" if self.failed else ""
        self.progress.update(self.bar, description=f"patients{failed}  {active}")


def _progress() -> Progress:
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total}"),
        TimeElapsedColumn(),
        console=console,
        transient=False,
    )


class _PlainReporter:
    """For a pipe or a file: one plain line per finished stage (stage, time, cache hit).

    Each line is written whole, under a lock: the patient lanes report from their own
    threads, and ``print`` writes a line and its newline separately (an audit's log
    had two lanes' lines run together).
    """

    _lock = threading.Lock()

    def _say(self, line: str) -> None:
        with self._lock:
            sys.stdout.write(line + "\n")
            sys.stdout.flush()

    def __call__(self, event: Any) -> None:
        if event.status == "started":
            return
        if event.status == "cached":
            what = "cache hit"
        elif event.status == "done":  # wall clock, any wait for a worker included
            what = f"{event.seconds:.2f} s wall"
        elif event.status == "published":  # its stage says "published" or "up to date"
            self._say(f"{event.patient_id}\tpublish\t{event.stage}")
            return
        else:
            what = event.status
        self._say(f"{event.patient_id}\t{event.stage}\t{what}")


def _patient_exit_code(result: Any) -> int:
    """0 for status ok, :data:`EXIT_CHECK` for check (tumor3d.segmentation.review)."""
    return EXIT_CHECK if result.metrics.get("status") == "check" else 0


def print_summary(result: Any, truth_mm3: float | None = None) -> None:
    """Print a patient's volumes (mm3 and mL, by method), slices, stage times and status.

    The status comes last: ``ok``, or ``check`` with the reasons the tool's
    own checks doubt the result (:mod:`tumor3d.segmentation.review`).
    """
    from tumor3d.flows.patient import VOLUME_LABELS, VOLUME_METHODS
    from tumor3d.storage.patient_outputs import method_words, split_notes

    m = result.metrics
    # the title on a line of its own: a table's title wraps at the table's width, which
    # split the patient id from "Tumour volume, patient" in a piped log
    console.print(f"[italic]Tumour volume, patient {escape(result.patient_id)}[/]", soft_wrap=True)
    table = Table()
    table.add_column("method")
    table.add_column("volume (mm3)", justify="right")
    table.add_column("volume (mL)", justify="right")
    if truth_mm3 is not None:
        table.add_column("error vs truth", justify="right")
    for key in VOLUME_METHODS:
        row = [VOLUME_LABELS[key], f"{m[key]:,.1f}", f"{m[key] / 1000.0:.3f}"]
        if truth_mm3 is not None:
            row.append(f"{100.0 * (m[key] - truth_mm3) / truth_mm3:+.2f} %" if truth_mm3 else "-")
        table.add_row(*row)
    if truth_mm3 is not None:
        table.add_row("truth (phantom)", f"{truth_mm3:,.1f}", f"{truth_mm3 / 1000.0:.3f}", "")
    console.print(table)
    if m.get("measured"):
        console.print(f"what is measured: {escape(str(m['measured']))}")
    if method_words(m):
        console.print(f"segmentation method: {escape(method_words(m))}")
    console.print(
        "[dim]" + "; ".join(f"{VOLUME_LABELS[k]}: {d}" for k, d in VOLUME_METHODS.items()) + "[/]"
    )
    if m["faces_mc"] == 0:
        mesh_note = "no tumour found: no mesh, no render"
    else:
        mesh_note = (
            f"mesh {m['faces_mc']} faces -> {m['faces_simplified']} simplified"
            f"{'' if m['mesh_watertight'] else ' (NOT watertight)'}"
        )
    console.print(
        f"slices: {m['n_slices']} acquired, {m['n_abnormal_slices']} flagged abnormal, "
        f"{m['n_tumor_slices']} with tumour; slab (thickness + gap) "
        f"{m['slab_height_mm']:.2f} mm; {_slices_inserted(m['slices_between'])} per gap; "
        f"{mesh_note}"
    )
    times = Table(title="Stages", title_justify="left")
    times.add_column("stage")
    times.add_column("compute (s)", justify="right")
    times.add_column("this run", justify="right")
    for s in result.stages:
        times.add_row(
            s.stage,
            f"{s.compute_seconds:.2f}",
            "cache hit" if s.cached else f"{s.wall_seconds:.2f} s",
        )
    console.print(times)
    if getattr(result, "recomputed", None):  # published before: why stages ran again
        console.print(
            f"[dim]since the earlier result[/], {escape(str(result.recomputed))}", soft_wrap=True
        )
    reasons = split_notes(m.get("review_reasons"))
    for note in getattr(result, "notes", []):
        if note not in reasons:
            console.print(f"[dim]note:[/] {escape(note)}", soft_wrap=True)
    eq7 = m.get("eq7_slice_rule")
    if eq7:
        from tumor3d.metrics import EQ7_SLICE_RULES

        console.print(f"[dim]Eq. 7 slices ({eq7}): {EQ7_SLICE_RULES[eq7]}[/]")
    current = " (up to date: already published, nothing rewritten)" if result.up_to_date else ""
    console.print(f"outputs: [bold]{escape(result.output_dir)}[/]{current}")
    report = Path(result.output_dir) / "report.html"
    if report.is_file():  # a local output folder (an s3:// one is not checked here)
        console.print(f"report: [bold]{escape(str(report))}[/] (open in a browser)")
    status = str(m.get("status", "ok"))
    if reasons:
        console.print(
            f"status: {_status_text(status)}: the tool's own checks doubt this result; look "
            "before using it:",
            soft_wrap=True,
        )
        for reason in reasons:
            console.print(f"  [yellow]-[/] {escape(reason)}", soft_wrap=True)
    else:
        console.print(f"status: {_status_text(status)}")


#: The cohort table's headers of the volume methods (named in full in its title).
_SHORT_VOLUME_HEADERS = {
    "volume_eq7_mm3": "Eq. 7",
    "volume_voxel_mm3": "voxels",
    "volume_mesh_mm3": "mesh",
    "volume_mesh_simplified_mm3": "simplified",
}


def print_cohort_summary(result: Any) -> None:
    """Print each patient's status, volumes and notes; name the failures and the checks."""
    from tumor3d.flows.patient import VOLUME_LABELS
    from tumor3d.storage.cohort_report import row_notes

    table = Table(  # short headers, no column rules: eight columns fit 80 characters
        title=f"Cohort: {len(result.patients)} patients; volumes in mL by "
        + ", ".join(VOLUME_LABELS.values()),
        title_justify="left", box=box.SIMPLE_HEAD, pad_edge=False, collapse_padding=True,
    )  # fmt: skip
    # the ids in full (up to 16 characters on one line, longer ones folded, never cut with
    # an ellipsis): a narrow or piped console showed "phanto…" for every patient
    longest = max((len(p.patient_id) for p in result.patients), default=7)
    table.add_column("patient", min_width=min(longest, 16), overflow="fold")
    table.add_column("status", no_wrap=True)
    for key in VOLUME_LABELS:
        table.add_column(_SHORT_VOLUME_HEADERS[key], justify="right")
    table.add_column("cached", justify="right")
    table.add_column("notes", justify="right")
    for p in result.patients:
        if p.status != "failed":
            vols = [f"{p.metrics[k] / 1000.0:.3f}" for k in VOLUME_LABELS]
            hits = f"{sum(s.cached for s in p.stages)}/{len(p.stages)}"
            n = len(row_notes(p.metrics))
            notes = f"{n} (below)" if n else ""
            table.add_row(escape(p.patient_id), _status_text(p.status), *vols, hits, notes)
        else:
            table.add_row(
                escape(p.patient_id), _status_text("failed"), *["-"] * len(VOLUME_LABELS), "-", ""
            )
    console.print(table)
    for p in result.patients:
        if p.status == "failed":
            continue
        reasons = row_notes({"review_reasons": p.metrics.get("review_reasons")})
        for note in row_notes(p.metrics):
            what = "[yellow]check[/]" if note in reasons else "[dim]note[/]"
            console.print(f"{what} {escape(p.patient_id)}: {escape(note)}", soft_wrap=True)
    for p in result.failed:
        console.print(
            f"[red]failed[/] {escape(p.patient_id)} at {escape(str(p.failed_stage))}: "
            f"{escape(str(p.error))}",
            soft_wrap=True,
        )
    if result.earlier:
        console.print(
            f"[yellow]earlier result kept[/] (this run failed before publishing, so the "
            f"folder is not this input's): {escape(', '.join(result.earlier))}",
            soft_wrap=True,
        )
    for why, ids in getattr(result, "since_earlier", {}).items():  # published before: why
        console.print(
            f"[dim]since the earlier result[/], {escape(why)}: {escape(', '.join(ids))}",
            soft_wrap=True,
        )
    if result.removed:
        console.print(
            f"[yellow]no longer in the manifest[/] (published earlier, folders kept): "
            f"{escape(', '.join(result.removed))}",
            soft_wrap=True,
        )
    n_check = sum(p.status == "check" for p in result.patients)
    n_ok = len(result.patients) - len(result.failed) - n_check
    console.print(
        f"{n_ok} ok, {n_check} to check, {len(result.failed)} failed in "
        f"{result.wall_seconds:.1f} s; outputs: [bold]{escape(result.out_dir)}[/] "
        "(cohort.parquet, cohort.md, cohort.html)"
    )
