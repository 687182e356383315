"""The ``tumor3d`` command line.

Commands: ``run`` (one patient), ``cohort`` (every patient of a manifest,
N at a time), ``demo`` (a built-in phantom patient end to end), ``phantom``
(write synthetic patients and a cohort manifest), ``server start|stop|status``
(one local Prefect server in the background, which later commands use; see
:mod:`tumor3d.flows.server`).

Exit codes (every error is one line on stderr naming the file and the
problem, never a traceback; nothing is published under the final names):

* 0 -- success: every result has status ``ok``;
* 1 -- ``cohort``/``evaluate``: some patients failed (the summary names them;
  a manifest row whose image is missing is such a failure);
* 2 -- bad input: a missing or unreadable file, an unsafe patient id, an
  invalid configuration or manifest, an output folder that holds the input
  or is a file, more voxels than ``--max-voxels``, a ``--brain-mask`` that is
  not on the image's grid, empty, non-finite or off the image;
* 3 -- environment error: the artifact store or an output folder cannot be
  written (a full disk, a read-only mount, no permission), a corrupted store
  object that could not be repaired, a Prefect server that cannot be started
  or reached (:data:`EXIT_ENVIRONMENT`);
* 4 -- ``run``/``demo``/``cohort``: every result was published, but some has
  status ``check``: the tool's own checks doubt it (a segmentation caveat, a
  brain mask that makes the volume unreliable, skipped files, a segmentation
  that asks for review); the summary says why (:data:`EXIT_CHECK`,
  :mod:`tumor3d.segmentation.review`). A cohort with failures exits 1.

User-supplied strings are escaped before Rich prints them. When stdout is not
a terminal, progress is one plain line per stage instead of a progress bar.
"""

from __future__ import annotations

import os
import sys

# Prefect's own INFO logs would interleave with the progress bar; they stay
# available with --verbose and always reach the Prefect server. This must be
# set before Prefect is first imported.
if "--verbose" not in sys.argv and "-v" not in sys.argv:
    os.environ.setdefault("PREFECT_LOGGING_LEVEL", "WARNING")
os.environ.setdefault("PREFECT_SERVER_ANALYTICS_ENABLED", "false")

from collections.abc import Iterator  # noqa: E402
from contextlib import contextmanager  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Annotated, Any  # noqa: E402

import typer  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.markup import escape  # noqa: E402
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn  # noqa: E402
from rich.table import Table  # noqa: E402

from tumor3d.constants import MAX_VOXELS_DEFAULT  # noqa: E402
from tumor3d.errors import Tumor3DError  # noqa: E402

app = typer.Typer(
    name="tumor3d",
    help="3-D reconstruction and volume of brain tumours from thick-slice MR "
    "(Arakeri & Reddy 2013), as cached Prefect workflows.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
)
console = Console()
err_console = Console(stderr=True)


def _print_version(value: bool) -> None:
    if value:
        from tumor3d import __version__

        console.print(f"tumor3d {__version__}", highlight=False)
        raise typer.Exit()


@app.callback()
def _main(
    version: Annotated[
        bool,
        typer.Option(
            "--version",
            callback=_print_version,
            is_eager=True,
            help="Print the installed version and exit.",
        ),
    ] = False,
) -> None:
    """3-D reconstruction and volume of brain tumours from thick-slice MR (Arakeri & Reddy 2013)."""


#: Exit code of bad input (a file, option, configuration or manifest the user gave).
EXIT_INPUT = 2
#: Exit code of environment errors: store or output not writable, server unavailable.
EXIT_ENVIRONMENT = 3
#: Exit code of results published with status ``check`` (a human should look).
EXIT_CHECK = 4
#: Exit code of a command stopped by Ctrl-C (128 + SIGINT, as a shell reports it).
EXIT_INTERRUPTED = 130
#: Rich style of each status (tumor3d.segmentation.review).
_STATUS_STYLE = {"ok": "bold green", "check": "bold yellow", "failed": "bold red"}


def _status_text(status: str) -> str:
    return f"[{_STATUS_STYLE.get(status, 'bold')}]{escape(status)}[/]"


def _error_line(exc: BaseException) -> tuple[str, int]:
    """The one-line message and the exit code of an error that ends a command."""
    if isinstance(exc, OSError):
        from tumor3d.errors import os_error_text

        where = f"{exc.filename}: " if exc.filename else ""
        return f"{where}{os_error_text(exc)}", EXIT_ENVIRONMENT
    from tumor3d.flows.dask_runner import ClusterError
    from tumor3d.flows.server import ServerError
    from tumor3d.storage.store import StoreError

    environment = StoreError | ServerError | ClusterError
    code = EXIT_ENVIRONMENT if isinstance(exc, environment) else EXIT_INPUT
    return str(exc) or type(exc).__name__, code


def _fail(exc: BaseException) -> typer.Exit:
    text, code = _error_line(exc)
    err_console.print(f"[bold red]error:[/] {escape(text)}", highlight=False, soft_wrap=True)
    return typer.Exit(code=code)


#: What the commands catch and turn into one line (anything else is a bug: traceback).
_HANDLED = (Tumor3DError, OSError)


@contextmanager
def _ctrl_c_ends(message: str) -> Iterator[None]:
    """Ctrl-C (SIGINT) ends the command at once: one line on stderr, exit code 130.

    Python's KeyboardInterrupt did not stop a cohort: the main thread's
    interrupt waited for every patient lane to finish, and those lanes (with
    Prefect's event and log services) retried for minutes against the
    temporary Prefect server, which the same Ctrl-C had stopped (it shares
    the terminal's process group), printing their tracebacks. Here the
    process exits instead: nothing is published half (a patient is staged in
    a hidden folder and renamed at the end; a staging folder of this ended
    process is removed by the next publish of that patient), the temporary
    server dies with its parent (:mod:`tumor3d.flows.server`), and Prefect's unsent
    events are dropped. Install from the main thread only.
    """
    import signal

    def on_sigint(signum: int, frame: Any) -> None:
        try:
            if console.is_terminal:
                console.show_cursor(True)  # a live progress bar hides it
            for stream in (sys.stdout, sys.stderr):
                stream.flush()
            sys.stderr.write(("\n" if console.is_terminal else "") + f"interrupted: {message}\n")
            sys.stderr.flush()
        finally:
            os._exit(EXIT_INTERRUPTED)

    previous = signal.signal(signal.SIGINT, on_sigint)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def _load_config(path: Path | None) -> dict[str, Any]:
    from tumor3d.config import parse_config
    from tumor3d.errors import ConfigError

    if path is None:
        return {}
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(f"cannot read configuration: {exc.strerror}", path=str(path)) from None
    except UnicodeDecodeError as exc:
        raise ConfigError(
            f"not UTF-8 text (byte 0x{exc.object[exc.start]:02x} at offset {exc.start})",
            path=str(path),
        ) from None
    return parse_config(text, source=str(path)).model_dump(mode="json")


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
    """For a pipe or a file: one plain line per finished stage (stage, time, cache hit)."""

    def __call__(self, event: Any) -> None:
        if event.status == "started":
            return
        if event.status == "cached":
            what = "cache hit"
        elif event.status == "done":
            what = f"{event.seconds:.2f} s"
        else:
            what = event.status
        print(f"{event.patient_id}\t{event.stage}\t{what}", flush=True)


def _patient_exit_code(result: Any) -> int:
    """0 for status ok, :data:`EXIT_CHECK` for check (tumor3d.segmentation.review)."""
    return EXIT_CHECK if result.metrics.get("status") == "check" else 0


def print_summary(result: Any, truth_mm3: float | None = None) -> None:
    """Print a patient's volumes (mm3 and mL, by method), slices, stage times and status.

    The status comes last: ``ok``, or ``check`` with the reasons the tool's
    own checks doubt the result (:mod:`tumor3d.segmentation.review`).
    """
    from tumor3d.flows.patient import VOLUME_LABELS, VOLUME_METHODS
    from tumor3d.storage.patient_outputs import split_notes

    m = result.metrics
    table = Table(title=f"Tumour volume, patient {escape(result.patient_id)}", title_justify="left")
    table.add_column("method")
    table.add_column("volume (mm3)", justify="right")
    table.add_column("volume (mL)", justify="right")
    if truth_mm3 is not None:
        table.add_column("error vs truth", justify="right")
    for key in VOLUME_METHODS:
        row = [VOLUME_LABELS[key], f"{m[key]:,.1f}", f"{m[key] / 1000.0:.3f}"]
        if truth_mm3 is not None:
            row.append(f"{100.0 * abs(m[key] - truth_mm3) / truth_mm3:.2f} %" if truth_mm3 else "-")
        table.add_row(*row)
    if truth_mm3 is not None:
        table.add_row("truth (phantom)", f"{truth_mm3:,.1f}", f"{truth_mm3 / 1000.0:.3f}", "")
    console.print(table)
    if m.get("measured"):
        console.print(f"what is measured: {escape(str(m['measured']))}")
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
        f"{m['slab_height_mm']:.2f} mm; {m['slices_between']} slices inserted per gap; "
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
    from tumor3d.storage.objectstore import default_store_location, is_url, open_store
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
    from tumor3d.flows.server import check_configured_api
    from tumor3d.storage.store import ArtifactStore

    check_configured_api()  # an unreachable PREFECT_API_URL: one line, nothing created
    if store is not None and is_url(store):
        open_store(str(store)).check()  # type: ignore[attr-defined]
    else:
        ArtifactStore(store if store is not None else default_store_location(out))


def _preflight_remote(
    input_path: Path,
    out: str,
    options: Any,
    store: str | Path | None = None,
    brain_mask: Path | None = None,
    segmentation: Path | None = None,
) -> None:
    """:func:`_preflight` for an ``s3://`` output: inputs are local, so none can lie in it."""
    from tumor3d.storage.objectstore import default_store_location, is_url, open_store
    from tumor3d.storage.readers.handoff import read_and_keep
    from tumor3d.storage.remote_publish import RemoteFolder
    from tumor3d.storage.store import ArtifactStore

    scan = read_and_keep(input_path, options)  # the ingest stage takes it: one read
    _check_given_masks(scan, brain_mask, segmentation, options.max_voxels)
    from tumor3d.flows.server import check_configured_api

    check_configured_api()  # an unreachable PREFECT_API_URL: one line, nothing created
    RemoteFolder(out).check()  # one line naming the URL
    at = store if store is not None else default_store_location(out)
    if is_url(at):
        open_store(str(at)).check()  # type: ignore[attr-defined]
    else:
        ArtifactStore(at)


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


#: The modality ``run`` assumes when --modality is not given (said on the console).
DEFAULT_MODALITY = "t2"


def _say_modality(modality: str, assumed: bool) -> None:
    """Say the modality the run used, and that it was the default when it was."""
    if not assumed:
        console.print(f"modality: {escape(modality)}", highlight=False)
        return
    console.print(
        f"modality: [bold]{escape(modality)}[/] (the default: --modality was not given; it "
        "decides the segmentation, so give --modality flair or t1c for those images)",
        highlight=False, soft_wrap=True,
    )  # fmt: skip


def _check_out_dir(out: Path) -> None:
    """An output folder that exists as a file is bad input (exit 2), found before any work."""
    from tumor3d.errors import InputError

    if out.exists() and not out.is_dir():
        raise InputError("the output folder (--out) is a file, not a folder", str(out))


def _starting_prefect_note() -> None:
    console.print(
        "[dim]starting Prefect: a temporary local server for this command (10-20 s; "
        "`tumor3d server start` keeps one running for fast repeated runs)...[/]"
    )


class _NoFailureTracebacks:
    """Console filter: drop Prefect's own records of flow and task runs (any level).

    Their warnings and errors repeat, under a run name and with a traceback,
    what the command prints itself as one line (a failed patient, a skipped
    row, a patient no longer in the manifest); they still reach the Prefect
    server (its API handler is not filtered), and ``--verbose`` shows them.
    """

    def filter(self, record: Any) -> bool:
        name = record.name
        return not name.startswith(("prefect.flow_runs", "prefect.task_runs"))


def _quiet_prefect_failures() -> None:
    import logging

    from prefect.logging.configuration import ensure_logging_setup

    if "--verbose" in sys.argv or "-v" in sys.argv:
        return
    ensure_logging_setup()
    for handler in logging.getLogger().handlers:
        if not any(isinstance(f, _NoFailureTracebacks) for f in handler.filters):
            handler.addFilter(_NoFailureTracebacks())


@contextmanager
def _no_heartbeats() -> Iterator[None]:
    """Flow-run heartbeats off for a command, unless PREFECT_FLOWS_HEARTBEAT_FREQUENCY is set.

    Prefect's heartbeat thread sleeps in 1 s steps and the flow engine joins
    it when the run ends: about 0.9 s of every command, for a signal that
    only a server automation (not set up by default) would use.
    """
    if os.environ.get("PREFECT_FLOWS_HEARTBEAT_FREQUENCY"):
        yield
        return
    from prefect.settings import temporary_settings

    with temporary_settings(updates={"flows.heartbeat_frequency": None}):
        yield


@contextmanager
def _prefect() -> Iterator[str]:
    """PREFECT_API_URL, else the background server, else a temporary one (flows.server)."""
    from tumor3d.flows.server import prefect_api

    with prefect_api(on_temporary_start=_starting_prefect_note) as api_url, _no_heartbeats():
        _quiet_prefect_failures()
        yield api_url


@contextmanager
def _reporting(make_reporter: Any) -> Iterator[None]:
    """A live progress bar on a terminal, plain lines otherwise."""
    from tumor3d.flows.progress import use_reporter

    if not console.is_terminal:
        with use_reporter(_PlainReporter()):
            yield
        return
    with _progress() as progress, use_reporter(make_reporter(progress)):
        yield


def _run_with_progress(**kwargs: Any) -> Any:
    from tumor3d.flows.patient import run_patient

    with _prefect(), _reporting(_ProgressReporter):
        return run_patient(**kwargs)


Verbose = Annotated[bool, typer.Option("--verbose", "-v", help="Show Prefect's own logs.")]
MaxVoxels = Annotated[
    int,
    typer.Option(
        "--max-voxels",
        min=1,
        help="Refuse an input whose header declares more voxels than this, before reading it "
        "(default 512 million, far above any MR series).",
    ),
]
DaskAddress = Annotated[
    str | None,
    typer.Option(help="Run the stages on an existing Dask scheduler, tcp://HOST:PORT."),
]
DaskWorkers = Annotated[
    int | None,
    typer.Option(min=1, help="Run the stages on a temporary local Dask cluster of N workers."),
]
Workers = Annotated[
    int | None, typer.Option(min=1, help="Patients at a time (default: the CPU cores).")
]
Layout = Annotated[
    str,
    typer.Option(
        "--layout",
        help="default: OUT/<id>/ as tumor3d names it; bids: BIDS derivatives, "
        "OUT/sub-<label>/anat/sub-<label>_desc-tumor_mask.nii.gz ... with JSON sidecars and "
        "OUT/dataset_description.json (the label: the id's letters and digits).",
    ),
]
CohortStore = Annotated[
    str | None,
    typer.Option(
        help="Artifact store: a folder or s3://bucket/prefix (default OUT/.tumor3d-store)."
    ),
]


@app.command()
def run(
    input_path: Annotated[
        Path,
        typer.Argument(
            help="NIfTI, NRRD or MetaImage file, DICOM series folder, or folder of 2-D slices."
        ),
    ],
    out: Annotated[str, typer.Option("--out", "-o", help="Output folder, or s3://bucket/prefix.")],
    patient_id: Annotated[
        str | None, typer.Option(help="Folder-safe patient id (default: from the input name).")
    ] = None,
    config: Annotated[Path | None, typer.Option(help="YAML configuration file.")] = None,
    modality: Annotated[
        str | None,
        typer.Option(help="t2, flair or t1c (default t2, said on the console when assumed)."),
    ] = None,
    slice_thickness_mm: Annotated[
        float | None, typer.Option(help="Override the slice thickness (mm).")
    ] = None,
    slice_gap_mm: Annotated[float | None, typer.Option(help="Override the slice gap (mm).")] = None,
    series_uid: Annotated[
        str | None, typer.Option(help="DICOM SeriesInstanceUID when a folder holds several.")
    ] = None,
    store: CohortStore = None,
    skip_unreadable_dicom: Annotated[
        bool,
        typer.Option(
            help="Skip DICOM files that cannot be read (named in the summary) instead of stopping."
        ),
    ] = False,
    max_voxels: MaxVoxels = MAX_VOXELS_DEFAULT,
    brain_mask: Annotated[
        Path | None,
        typer.Option(
            "--brain-mask",
            help="A brain mask on the input's voxel grid (same shape and affine; brain = "
            "values > 0.5: a 0/1 or 0/255 mask or a probability map) used instead of skull "
            "removal.",
        ),
    ] = None,
    segmentation: Annotated[
        Path | None,
        typer.Option(
            "--segmentation",
            help="Your own tumour mask on the input's voxel grid (same shape and affine; "
            "tumour = values > 0.5), used instead of the tool's segmentation; meshes, volumes, "
            "renders and report are made from it.",
        ),
    ] = None,
    layout: Layout = "default",
    verbose: Verbose = False,
) -> None:
    """Reconstruct one patient's tumour: masks, meshes, renders and volumes under OUT/<id>/."""
    from tumor3d.storage.readers.handoff import forget_kept
    from tumor3d.storage.readers.options import ReadOptions

    try:
        cfg = _load_config(config)
        assumed = modality is None
        modality = DEFAULT_MODALITY if modality is None else modality
        options = ReadOptions(  # the reading options, checked once and passed on as one
            modality=modality, patient_id=patient_id, series_uid=series_uid,
            slice_thickness_mm=slice_thickness_mm, slice_gap_mm=slice_gap_mm,
            skip_unreadable=skip_unreadable_dicom, max_voxels=max_voxels,
        )  # fmt: skip
        _preflight(input_path, out, options, store, brain_mask, segmentation, layout)
        result = _run_with_progress(
            input_path=input_path,
            out_dir=_location(out),
            config=cfg,
            store_dir=None if store is None else str(store),
            brain_mask=None if brain_mask is None else str(brain_mask),
            segmentation=None if segmentation is None else str(segmentation),
            layout=layout,
            **options.model_dump(),
        )
    except _HANDLED as exc:
        raise _fail(exc) from None
    finally:
        forget_kept()  # a scan the ingest stage did not need (its result was cached)
    _say_modality(modality, assumed)
    print_summary(result)
    raise typer.Exit(code=_patient_exit_code(result))


@app.command()
def cohort(
    manifest: Annotated[Path, typer.Argument(help="Cohort manifest CSV (patient_id, image, ...).")],
    out: Annotated[str, typer.Option("--out", "-o", help="Output folder, or s3://bucket/prefix.")],
    config: Annotated[Path | None, typer.Option(help="YAML configuration file.")] = None,
    workers: Workers = None,
    store: CohortStore = None,
    max_voxels: MaxVoxels = MAX_VOXELS_DEFAULT,
    dask_address: DaskAddress = None,
    dask_workers: DaskWorkers = None,
    layout: Layout = "default",
    verbose: Verbose = False,
) -> None:
    """Run every patient of a manifest, N at a time: OUT/<id>/, OUT/cohort.parquet, OUT/cohort.md.

    Exit code 0 when every patient succeeded with status ok, 1 when some failed
    (named in the summary; a row whose image is missing fails alone), 4 when
    none failed but some has status check (the notes say why), 2 for an invalid
    manifest or configuration, 3 for an environment error (an unwritable
    output, an unreachable Dask scheduler or object store, a Prefect server
    that cannot start).
    """
    from tumor3d.flows.cohort import run_cohort
    from tumor3d.flows.dask_runner import DaskSpec
    from tumor3d.storage.manifest import read_manifest
    from tumor3d.storage.objectstore import is_url

    try:
        cfg = _load_config(config)
        if not is_url(out):  # an object-store URL is checked by run_cohort
            _check_out_dir(Path(out))
        rows = read_manifest(manifest, require_files=False)
        dask = DaskSpec(dask_address, dask_workers)
        stopped = (
            "Ctrl-C stopped the cohort; the patients published before it are complete, "
            "a re-run continues from the cache"
        )
        with (
            _ctrl_c_ends(stopped),
            _prefect(),
            _reporting(lambda progress: _CohortReporter(progress, len(rows))),
        ):
            result = run_cohort(
                rows, out, config=cfg, workers=workers, max_voxels=max_voxels,
                store_dir=store, dask=dask, layout=layout,
            )  # fmt: skip
    except _HANDLED as exc:
        raise _fail(exc) from None
    print_cohort_summary(result)
    raise typer.Exit(code=result.exit_code)


@app.command()
def serve(
    manifest: Annotated[
        Path, typer.Argument(help="Cohort manifest CSV, re-read by every scheduled run.")
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")],
    cron: Annotated[str, typer.Option(help='Cron schedule, e.g. "0 2 * * *" (02:00 every day).')],
    name: Annotated[
        str, typer.Option(help="Deployment name (shown in the Prefect UI).")
    ] = "tumor3d-cohort-nightly",
    timezone: Annotated[str, typer.Option(help="Time zone of the cron schedule.")] = "UTC",
    config: Annotated[
        Path | None, typer.Option(help="YAML configuration file, re-read by every run.")
    ] = None,
    workers: Workers = None,
    store: CohortStore = None,
    dask_address: DaskAddress = None,
    dask_workers: DaskWorkers = None,
    verbose: Verbose = False,
) -> None:
    """Serve the cohort flow as a Prefect deployment on a cron schedule (blocks).

    Each run re-reads the manifest: new or changed inputs compute, unchanged
    ones come from the cache, patients no longer listed are reported in
    OUT/cohort.md (their folders are kept). Runs can also be triggered from the
    Prefect UI. Set PREFECT_API_URL to a persistent Prefect server (see README).
    """
    from tumor3d.flows.serve import cohort_deployment, serve_cohort

    try:
        deployment = cohort_deployment(
            manifest, out, cron=cron, name=name, config_path=config, workers=workers,
            store_dir=store, dask_address=dask_address, dask_workers=dask_workers,
            timezone=timezone,
        )  # fmt: skip
    except _HANDLED as exc:
        raise _fail(exc) from None
    from tumor3d.flows.server import prefect_api

    def temporary_note() -> None:
        console.print(
            "[yellow]no Prefect server configured (PREFECT_API_URL) or running (`tumor3d server "
            "start`): serving against a temporary local server that stops with this command "
            "(see README, Scheduled reprocessing).[/]"
        )

    try:
        with prefect_api(on_temporary_start=temporary_note) as api_url:
            console.print(
                f"serving deployment [bold]tumor3d-scheduled-cohort/{escape(name)}[/] "
                f"(cron {escape(cron)} {escape(timezone)}) on {escape(api_url)}; Ctrl-C to stop"
            )
            serve_cohort(deployment)
    except _HANDLED as exc:
        raise _fail(exc) from None


def print_cohort_summary(result: Any) -> None:
    """Print each patient's status, volumes and notes; name the failures and the checks."""
    from tumor3d.flows.patient import VOLUME_LABELS
    from tumor3d.storage.cohort_report import row_notes

    table = Table(title=f"Cohort: {len(result.patients)} patients", title_justify="left")
    table.add_column("patient")
    table.add_column("status")
    for key in VOLUME_LABELS:
        table.add_column(f"{VOLUME_LABELS[key]} (mL)", justify="right")
    table.add_column("cache hits", justify="right")
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


@app.command()
def demo(
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")] = Path("demo-out"),
    seed: Annotated[int, typer.Option(help="Phantom seed.")] = 7,
    config: Annotated[Path | None, typer.Option(help="YAML configuration file.")] = None,
    verbose: Verbose = False,
) -> None:
    """Generate a built-in phantom patient with known tumour volume and reconstruct it."""
    import json

    from tumor3d.phantom import make_phantom_patient
    from tumor3d.storage.phantom_io import write_phantom_patient

    try:
        cfg = _load_config(config)
        _check_out_dir(out)
        console.print(f"generating phantom patient (seed {seed})...")
        patient = make_phantom_patient(seed, patient_id=f"demo{seed:03d}")
        row = write_phantom_patient(patient, out / "inputs")
        truth = json.loads(
            (row.image.parent / f"{patient.scan.patient_id}_truth.json").read_text()
        )["true_volume_mm3"]
        result = _run_with_progress(
            input_path=row.image, out_dir=out, patient_id=row.patient_id, config=cfg,
            modality=row.modality,
        )  # fmt: skip
    except _HANDLED as exc:
        raise _fail(exc) from None
    print_summary(result, truth_mm3=truth)
    raise typer.Exit(code=_patient_exit_code(result))


@app.command()
def phantom(
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")],
    n: Annotated[int, typer.Option("--n", min=1, help="Number of patients.")] = 5,
    seed: Annotated[int, typer.Option(help="Seed of the first patient.")] = 0,
    normal: Annotated[
        int, typer.Option(min=0, help="How many of the N patients have no tumour.")
    ] = 0,
    preset: Annotated[str, typer.Option(help="default (256x256) or paper (640x480).")] = "default",
    modality: Annotated[str, typer.Option(help="t2 or flair contrast.")] = "t2",
) -> None:
    """Write N synthetic patients with known tumour volume and a cohort manifest."""
    from tumor3d.phantom import make_phantom_patient
    from tumor3d.storage.phantom_io import write_phantom_cohort

    if normal > n:
        raise _fail(ValueError(f"--normal ({normal}) cannot exceed --n ({n})"))
    try:
        _check_out_dir(out)
        patients = []
        with _progress() as progress:
            bar = progress.add_task("generating phantoms", total=n)
            for i in range(n):
                is_normal = i >= n - normal
                patients.append(
                    make_phantom_patient(
                        seed + i,
                        preset=preset,
                        modality=modality,
                        tumor=not is_normal,
                        patient_id=f"phantom{seed + i:03d}{'n' if is_normal else ''}",
                    )
                )
                progress.advance(bar)
        manifest = write_phantom_cohort(patients, out)
    except _HANDLED as exc:
        raise _fail(exc) from None
    console.print(
        f"wrote {n} patients ({normal} without tumour) and manifest "
        f"[bold]{escape(str(manifest))}[/]"
    )


server_app = typer.Typer(
    help="One local Prefect server in the background, used by every later command "
    "(fast repeated runs; the runs appear in its UI). State in $TUMOR3D_HOME "
    "(default ~/.tumor3d): server.json, server.log.",
    no_args_is_help=True,
)
app.add_typer(server_app, name="server")


@server_app.command("start")
def server_start(
    port: Annotated[
        int | None, typer.Option(min=1, max=65535, help="Port (default: a free one).")
    ] = None,
) -> None:
    """Start the background Prefect server (or report the one already running)."""
    from tumor3d.flows.server import start_server

    try:
        info, started = start_server(port=port)
    except _HANDLED as exc:
        raise _fail(exc) from None
    what = "started" if started else "already running"
    console.print(
        f"Prefect server {what}: pid {info.pid}, API {escape(info.api_url)}, "
        f"UI {escape(info.api_url.removesuffix('/api'))}, log {escape(info.log)}",
        soft_wrap=True,
    )


@server_app.command("stop")
def server_stop() -> None:
    """Stop the background Prefect server (a stale state file is removed)."""
    from tumor3d.flows.server import stop_server

    try:
        before = stop_server()
    except _HANDLED as exc:
        raise _fail(exc) from None
    if before.state in ("running", "unhealthy") and before.info is not None:
        console.print(f"stopped the Prefect server (pid {before.info.pid})")
    elif before.state == "stale":
        console.print(f"no server was running; removed the {escape(before.line)}", soft_wrap=True)
    else:
        console.print("no tumor3d Prefect server was running")


@server_app.command("status")
def server_status_cmd() -> None:
    """Say whether the background server runs, where, and whether it is healthy.

    Exit code 0 when it is running and healthy, 1 otherwise.
    """
    from tumor3d.flows.server import server_status

    status = server_status()
    console.print(escape(status.line), soft_wrap=True, highlight=False)
    raise typer.Exit(code=0 if status.state == "running" else 1)


@app.command()
def methods() -> None:
    """List the segmentation methods (segment.method) and the input formats (their registries)."""
    from tumor3d.segmentation.methods import AUTO, registered_methods
    from tumor3d.storage.readers.registry import registered_readers

    table = Table(title="Segmentation methods (segment.method)", title_justify="left")
    for col in ("method", "what it is", "modalities"):
        table.add_column(col)
    table.add_row(AUTO, "the default: picks one of the below by modality (see the README)", "")
    for m in sorted(registered_methods().values(), key=lambda m: m.name):
        table.add_row(m.name, escape(m.description), ", ".join(m.modalities))
    console.print(table)
    formats = Table(title="Input formats", title_justify="left")
    for col in ("reader", "give"):
        formats.add_column(col)
    for r in registered_readers().values():
        formats.add_row(r.name, escape(r.accepts))
    console.print(formats)


# ----------------------------------------------------------------- evaluate (EVAL helper's block)


@app.command()
def evaluate(
    manifest: Annotated[
        list[Path] | None, typer.Argument(help="Cohort manifest CSV(s) with reference columns.")
    ] = None,
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")] = Path("eval-out"),
    config: Annotated[
        list[str] | None,
        typer.Option(
            help="NAME=FILE (or FILE); repeat to evaluate several configurations side by side."
        ),
    ] = None,
    workers: Annotated[
        int | None, typer.Option(min=1, help="Patients at a time (default: the cores).")
    ] = None,
    store: Annotated[
        Path | None, typer.Option(help="Artifact store (default OUT/.tumor3d-store).")
    ] = None,
    phantoms: Annotated[
        int, typer.Option(min=0, help="Also generate N phantom patients (truth as reference).")
    ] = 0,
    evaluation: Annotated[
        list[str] | None,
        typer.Option(
            help="Registered evaluation to run (repeat): segmentation (the default), "
            "interpolation (Table 4 on the references), simplification (Figure 10)."
        ),
    ] = None,
    verbose: Verbose = False,
) -> None:
    """Run the cohort and compare each patient with its reference: OUT/REPORT.md and tables.

    Exit code 0 when every row was evaluated (rows whose files are absent are
    skipped with a message), 1 when some row was invalid or some patient
    failed, 2 for an unreadable manifest or configuration.
    """
    import shlex

    # A cohort on a busy machine: give the temporary Prefect server time to start.
    os.environ.setdefault("PREFECT_SERVER_EPHEMERAL_STARTUP_TIMEOUT_SECONDS", "180")
    from tumor3d.flows.evaluate import _load_configs, parse_config_specs, run_evaluation
    from tumor3d.storage.manifest import read_manifest_rows

    manifest = manifest or []
    if not manifest and not phantoms:
        raise _fail(ValueError("give at least one MANIFEST or --phantoms N"))
    try:
        specs = parse_config_specs(config)
        _load_configs(specs)  # fail fast on a bad configuration
        from tumor3d.evaluation import selected_evaluations

        selected_evaluations(evaluation)  # fail fast on an unknown evaluation
        for m in manifest:
            read_manifest_rows(m)  # fail fast on a bad manifest (header, missing file)
        command = "tumor3d " + " ".join(shlex.quote(a) for a in sys.argv[1:])
        with _prefect():
            result = run_evaluation(
                manifest, out, config_files=specs, workers=workers,
                store_dir=None if store is None else str(store), phantoms=phantoms,
                command=command, evaluations=evaluation,
            )  # fmt: skip
    except _HANDLED as exc:
        raise _fail(exc) from None
    for s in result.skipped:
        tag = "skipped (file absent)" if s["missing_file"] else "invalid row"
        err_console.print(f"[yellow]{tag}:[/] {s['reason']}", highlight=False, soft_wrap=True)
    df = result.patients
    table = Table(title="Evaluation", title_justify="left")
    for col in ("config", "patient", "status", "slice Dice", "3-D Dice", "HD95 mm", "Eq. 7 err"):
        table.add_column(col)
    for _, r in df.iterrows():

        def cell(key: str, fmt: str, _r: Any = r) -> str:
            v = _r.get(key)
            return "-" if v is None or v != v else fmt.format(v)

        table.add_row(
            str(r["config"]), str(r["patient_id"]), str(r["status"]),
            cell("dice_slices_mean", "{:.3f}"), cell("dice_3d", "{:.3f}"),
            cell("hd95_mm", "{:.1f}"), cell("volume_eq7_error_percent", "{:+.1f} %"),
        )  # fmt: skip
    console.print(table)
    console.print(f"report: [bold]{result.report}[/]")
    if result.n_failed or result.n_invalid:
        raise typer.Exit(code=1)


# ----------------------------------------------------------------- end of evaluate block


@app.command()
def train(
    manifest: Annotated[
        Path, typer.Argument(help="Manifest CSV of labelled patients (a reference column).")
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the models.")],
    config: Annotated[Path | None, typer.Option(help="YAML configuration file.")] = None,
    store: Annotated[
        Path | None, typer.Option(help="Artifact store (default OUT/.tumor3d-store).")
    ] = None,
    threshold: Annotated[
        float, typer.Option(min=0.0, max=1.0, help="FLAIR/T2 model's probability threshold.")
    ] = 0.5,
    t1c_threshold: Annotated[
        float, typer.Option(min=0.0, max=1.0, help="T1c model's probability threshold.")
    ] = 0.65,
    keep_fraction: Annotated[
        float, typer.Option(min=0.0, max=1.0, help="Keep lesion parts this fraction of the main.")
    ] = 1.0,
    rounds: Annotated[int, typer.Option(min=1, help="Boosting rounds.")] = 150,
    cnn: Annotated[
        bool, typer.Option("--cnn", help="Also train the FLAIR U-Net: OUT/unet_flair.npz (torch).")
    ] = False,
    verbose: Verbose = False,
) -> None:
    """Train the learned segmentation on labelled patients: OUT/<family>.npz, OUT/training.json.

    Every row needs a reference (or reference_kind tumor_free); emulate_step_mm rows
    are emulated as the evaluation does. Each patient's stages are cached like a
    cohort's. Needs the train extra (pip install 'tumor3d[train]'; --cnn needs its
    torch). Exit code 0, 2 for a bad manifest, row or configuration, 3 for an
    environment error.
    """
    import shlex

    from tumor3d.flows.train import run_training

    try:
        cfg = _load_config(config)
        _check_out_dir(out)
        command = "tumor3d " + " ".join(shlex.quote(a) for a in sys.argv[1:])
        with _ctrl_c_ends("Ctrl-C stopped the training; a re-run continues from the cache"):
            with _prefect():
                result = run_training(
                    manifest, out, config=cfg, store_dir=None if store is None else str(store),
                    threshold=threshold, t1c_threshold=t1c_threshold,
                    keep_fraction=keep_fraction, num_rounds=rounds, command=command, cnn=cnn,
                )  # fmt: skip
    except _HANDLED as exc:
        raise _fail(exc) from None
    table = Table(title="Training", title_justify="left")
    for col in ("model", "patients", "rows", "lesion rows", "file"):
        table.add_column(col)
    for family, path in result.models.items():
        if family == "unet_flair":  # its rows are slices
            cases = [c for c in result.cases if "unet_slices" in c]
            rows, lesion = "unet_slices", "unet_tumour_slices"
        else:
            cases = [c for c in result.cases if c.get("family") == family]
            rows, lesion = "rows", "lesion_rows"
        table.add_row(
            family, str(len(cases)), str(sum(c[rows] for c in cases)),
            str(sum(c[lesion] for c in cases)), escape(path),
        )  # fmt: skip
    console.print(table)
    console.print(
        f"{result.cached_patients} of {len(result.cases)} patients' stages from the cache; "
        f"card: [bold]{escape(str(Path(result.out_dir) / 'training.json'))}[/]"
    )


def finish_process() -> None:
    """Run every exit handler and flush the standard streams.

    The handlers: Prefect sends its buffered logs and events, ``logging``
    flushes its handlers.
    """
    import atexit

    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass


def run_command(args: list[str] | None = None, prog_name: str | None = None) -> int:
    """Run a command to its end (:func:`finish_process`); its exit code.

    ``sys.exit("message")`` prints the message and gives 1. Used by
    :func:`main` and by the warm runner's copy of itself (:mod:`tumor3d.flows.daemon`).
    """
    code: int | str | None = 0
    try:
        app(args=args, prog_name=prog_name)
    except SystemExit as exc:
        code = exc.code
    finish_process()
    if isinstance(code, str):  # sys.exit("message") prints it and exits 1
        print(code, file=sys.stderr, flush=True)
        code = 1
    return int(code or 0)


def main() -> None:  # pragma: no cover - console entry
    """Entry point (``tumor3d``, ``python -m tumor3d.flows.cli``): run the command, then exit fast.

    Once the command has finished and :func:`finish_process` has run, the
    process ends with :func:`os._exit`: tearing down the interpreter with
    Prefect, scipy, numba and VTK loaded takes another 1.2-1.6 s and does
    nothing useful. Every output is written and closed before this point.
    """
    os._exit(run_command())


if __name__ == "__main__":  # pragma: no cover
    main()
