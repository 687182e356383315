"""The ``tumor3d`` command line.

Commands: ``run`` (one patient), ``demo`` (a built-in phantom patient end to
end), ``phantom`` (write synthetic patients and a cohort manifest).

Errors a user can cause (a missing or unreadable file, an unsafe patient id,
an invalid configuration) are printed as one line naming the file and the
problem, with exit code 2; nothing is published under the final names.
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

from pathlib import Path  # noqa: E402
from typing import Annotated, Any  # noqa: E402

import typer  # noqa: E402
from rich.console import Console  # noqa: E402
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn  # noqa: E402
from rich.table import Table  # noqa: E402

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


def _fail(exc: BaseException) -> typer.Exit:
    err_console.print(f"[bold red]error:[/] {exc}", highlight=False, soft_wrap=True)
    return typer.Exit(code=2)


def _load_config(path: Path | None) -> dict[str, Any]:
    from tumor3d.config import parse_config
    from tumor3d.errors import ConfigError

    if path is None:
        return {}
    try:
        text = path.read_text()
    except OSError as exc:
        raise ConfigError(f"cannot read configuration: {exc.strerror}", path=str(path)) from None
    return parse_config(text, source=str(path)).model_dump(mode="json")


class _ProgressReporter:
    """Shows one progress bar per patient, advancing stage by stage."""

    def __init__(self, progress: Progress) -> None:
        self.progress = progress
        self.bars: dict[str, Any] = {}

    def __call__(self, event: Any) -> None:
        bar = self.bars.get(event.patient_id)
        if bar is None:
            bar = self.progress.add_task(event.patient_id, total=event.total)
            self.bars[event.patient_id] = bar
        if event.status == "started":
            self.progress.update(bar, description=f"{event.patient_id}: {event.stage}")
        else:
            note = "cached" if event.status == "cached" else f"{event.seconds:.1f} s"
            self.progress.update(
                bar,
                completed=event.index,
                description=f"{event.patient_id}: {event.stage} ({note})",
            )


def _progress() -> Progress:
    return Progress(
        TextColumn("{task.description}"),
        BarColumn(),
        TextColumn("{task.completed}/{task.total} stages"),
        TimeElapsedColumn(),
        console=console,
        transient=False,
    )


def print_summary(result: Any, truth_mm3: float | None = None) -> None:
    """Print a patient's volumes (mm3 and mL, by method), slices and stage times."""
    from flows.patient import VOLUME_LABELS, VOLUME_METHODS

    m = result.metrics
    table = Table(title=f"Tumour volume, patient {result.patient_id}", title_justify="left")
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
    console.print(f"outputs: [bold]{result.output_dir}[/]")


def _preflight(input_path: Path, patient_id: str | None, modality: str, **read_kw: Any) -> None:
    """Read the input once before starting Prefect, so bad input fails in a second."""
    from storage.readers import read_scan

    read_scan(input_path, modality=modality, patient_id=patient_id, **read_kw)


def _run_with_progress(**kwargs: Any) -> Any:
    from flows.patient import run_patient
    from flows.progress import use_reporter

    console.print(
        "[dim]starting Prefect (a temporary local server unless PREFECT_API_URL is set; "
        "10-20 s)...[/]"
    )
    with _progress() as progress, use_reporter(_ProgressReporter(progress)):
        return run_patient(**kwargs)


Verbose = Annotated[bool, typer.Option("--verbose", "-v", help="Show Prefect's own logs.")]


@app.command()
def run(
    input_path: Annotated[
        Path, typer.Argument(help="NIfTI file, DICOM series folder, or folder of 2-D slices.")
    ],
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")],
    patient_id: Annotated[
        str | None, typer.Option(help="Folder-safe patient id (default: from the input name).")
    ] = None,
    config: Annotated[Path | None, typer.Option(help="YAML configuration file.")] = None,
    modality: Annotated[str, typer.Option(help="t2, flair or t1c.")] = "t2",
    slice_thickness_mm: Annotated[
        float | None, typer.Option(help="Override the slice thickness (mm).")
    ] = None,
    slice_gap_mm: Annotated[float | None, typer.Option(help="Override the slice gap (mm).")] = None,
    series_uid: Annotated[
        str | None, typer.Option(help="DICOM SeriesInstanceUID when a folder holds several.")
    ] = None,
    store: Annotated[
        Path | None, typer.Option(help="Artifact store (default OUT/.tumor3d-store).")
    ] = None,
    verbose: Verbose = False,
) -> None:
    """Reconstruct one patient's tumour: masks, meshes, renders and volumes under OUT/<id>/."""
    try:
        cfg = _load_config(config)
        read_kw = {
            "series_uid": series_uid,
            "slice_thickness_mm": slice_thickness_mm,
            "slice_gap_mm": slice_gap_mm,
        }
        _preflight(input_path, patient_id, modality, **read_kw)
        result = _run_with_progress(
            input_path=input_path,
            out_dir=out,
            patient_id=patient_id,
            config=cfg,
            modality=modality,
            store_dir=None if store is None else str(store),
            **read_kw,
        )
    except Tumor3DError as exc:
        raise _fail(exc) from None
    print_summary(result)


@app.command()
def demo(
    out: Annotated[Path, typer.Option("--out", "-o", help="Output folder.")] = Path("demo-out"),
    seed: Annotated[int, typer.Option(help="Phantom seed.")] = 7,
    config: Annotated[Path | None, typer.Option(help="YAML configuration file.")] = None,
    verbose: Verbose = False,
) -> None:
    """Generate a built-in phantom patient with known tumour volume and reconstruct it."""
    import json

    from storage.phantom_io import write_phantom_patient
    from tumor3d.phantom import make_phantom_patient

    try:
        cfg = _load_config(config)
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
    except Tumor3DError as exc:
        raise _fail(exc) from None
    print_summary(result, truth_mm3=truth)


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
    from storage.phantom_io import write_phantom_cohort
    from tumor3d.phantom import make_phantom_patient

    if normal > n:
        raise _fail(ValueError(f"--normal ({normal}) cannot exceed --n ({n})"))
    try:
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
    except Tumor3DError as exc:
        raise _fail(exc) from None
    console.print(f"wrote {n} patients ({normal} without tumour) and manifest [bold]{manifest}[/]")


def main() -> None:  # pragma: no cover - console entry
    """Entry point."""
    app()


if __name__ == "__main__":  # pragma: no cover
    main()
