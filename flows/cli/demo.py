"""The ``demo`` and ``phantom`` commands: built-in phantom patients with known volumes."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any

import typer
from rich.markup import escape

from tumor3d.flows.cli.app import Verbose, _load_config, app, console
from tumor3d.flows.cli.errors import _HANDLED, _fail
from tumor3d.flows.cli.output import _patient_exit_code, _progress, print_summary
from tumor3d.flows.cli.preflight import _check_out_dir
from tumor3d.flows.cli.session import _run_with_progress


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

        def make(i: int) -> Any:
            is_normal = i >= n - normal
            return make_phantom_patient(
                seed + i,
                preset=preset,
                modality=modality,
                tumor=not is_normal,
                patient_id=f"phantom{seed + i:03d}{'n' if is_normal else ''}",
            )

        # the first before the bar: a bad --preset or --modality is its one line alone
        patients = [make(0)]
        with _progress() as progress:
            bar = progress.add_task("generating phantoms", total=n, completed=1)
            for i in range(1, n):
                patients.append(make(i))
                progress.advance(bar)
        manifest = write_phantom_cohort(patients, out)
    except _HANDLED as exc:
        raise _fail(exc) from None
    console.print(
        f"wrote {n} patients ({normal} without tumour) and manifest "
        f"[bold]{escape(str(manifest))}[/]"
    )
