"""The Typer application, its consoles, the options several commands share, the configuration."""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.console import Console

app = typer.Typer(
    name="tumor3d",
    help="3-D reconstruction and volume of brain tumours from thick-slice MR "
    "(Arakeri & Reddy 2013), as cached Prefect workflows.",
    no_args_is_help=True,
    add_completion=False,
    pretty_exceptions_enable=False,
    rich_markup_mode=None,  # click's help: wrapped to the terminal; Rich's tables cut names
)
#: Line width of a console whose stream is not a terminal (a pipe, a log file) and no
#: ``COLUMNS``: wide enough that an error, a path or a patient id stays on its line for
#: grep, where Rich would wrap at 80.
PIPED_WIDTH = 1000


def _console(*, stderr: bool = False) -> Console:
    stream = sys.stderr if stderr else sys.stdout
    try:
        piped = not stream.isatty()
    except (AttributeError, ValueError):  # replaced or closed
        piped = True
    wide = piped and "COLUMNS" not in os.environ
    return Console(stderr=stderr, width=PIPED_WIDTH if wide else None)


console = _console()
err_console = _console(stderr=True)


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


def _check_models(cfg: dict[str, Any], modalities: list[str]) -> None:
    """The ``segment.learned_models`` folder holds the forest of each modality that uses it."""
    from tumor3d.config import parse_config
    from tumor3d.storage.given_models import resolve_learned_models

    resolve_learned_models(parse_config(cfg), modalities)


def _load_config(path: Path | None) -> dict[str, Any]:
    from tumor3d.storage.given_models import read_config_file

    return {} if path is None else read_config_file(path).model_dump(mode="json")


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
