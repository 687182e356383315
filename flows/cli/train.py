"""The ``train`` command: the learned segmentation trained on labelled patients."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape
from rich.table import Table

from tumor3d.flows.cli.app import Verbose, _load_config, app, console
from tumor3d.flows.cli.errors import _HANDLED, _ctrl_c_ends, _fail
from tumor3d.flows.cli.preflight import _check_out_dir
from tumor3d.flows.cli.session import _prefect


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
        bool,
        typer.Option(
            "--cnn",
            help="Also train the FLAIR U-Net ensemble: OUT/unet_flair_seed{0,1}.npz (torch).",
        ),
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
        if family.startswith("unet_flair"):  # its rows are slices
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
