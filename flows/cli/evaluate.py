"""The ``evaluate`` command: the cohort against its references."""

from __future__ import annotations

import os
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any

import typer
from rich.table import Table

from tumor3d.evaluation.registry import Evaluation, registered_evaluations
from tumor3d.flows.cli.app import Verbose, _check_models, app, console, err_console
from tumor3d.flows.cli.errors import _HANDLED, _ctrl_c_ends, _fail
from tumor3d.flows.cli.session import _prefect
from tumor3d.storage.evaluation_report import run_status_cell


def _evaluation_help() -> str:
    """``--evaluation``'s help: the registered evaluations, the default ones first.

    >>> _evaluation_help().partition(": ")[2]
    'segmentation (the default), interpolation, simplification.'
    """
    every = sorted(registered_evaluations().values(), key=lambda ev: (not ev.default, ev.name))
    names = [f"{ev.name} (the default)" if ev.default else ev.name for ev in every]
    return f"Registered evaluation to run (repeat): {', '.join(names)}."


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
        typer.Option(help=_evaluation_help()),
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
        configs = _load_configs(specs)  # fail fast on a bad configuration
        from tumor3d.evaluation import selected_evaluations

        chosen = selected_evaluations(evaluation)  # fail fast on an unknown evaluation
        modalities = ["t2"] if phantoms else []  # the phantoms command's
        for m in manifest:
            rows, _ = read_manifest_rows(m)  # fail fast on a bad manifest (header, files)
            modalities += [r.modality or "t2" for r in rows if not r.segmentation]
        for cfg in configs.values():  # each models folder holds the scans' forests
            _check_models(cfg, modalities)
        command = "tumor3d " + " ".join(shlex.quote(a) for a in sys.argv[1:])
        stopped = "Ctrl-C stopped the evaluation; a re-run continues from the cache"
        with _ctrl_c_ends(stopped), _prefect():
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
    console.print(_evaluation_table(result.patients, chosen))
    console.print(f"report: [bold]{result.report}[/]")
    if result.n_failed or result.n_invalid:
        raise typer.Exit(code=1)


def _console_columns(df: Any, evaluations: Mapping[str, Evaluation]) -> list[tuple[str, str, str]]:
    """``(header, evaluation.parquet column, format)`` of the evaluations' console columns.

    A column only when some row has a value: ``--evaluation interpolation`` alone
    printed a table of dashes.
    """
    declared = [c for ev in evaluations.values() for c in ev.columns.console]
    keyed = [(c.label, key, c.fmt) for c in declared for key in c.keys]
    return [m for m in keyed if m[1] in df.columns and df[m[1]].notna().any()]


def _evaluation_table(df: Any, evaluations: Mapping[str, Evaluation] | None = None) -> Table:
    """The console's table of ``evaluation.parquet``.

    Its metric columns are those the evaluations (default: every registered one)
    declare for the console (:class:`tumor3d.evaluation.registry.ReportColumns`).
    """
    shown = _console_columns(df, registered_evaluations() if evaluations is None else evaluations)
    table = Table(title="Evaluation", title_justify="left")
    for col, key in (("config", "config"), ("patient", "patient_id")):
        # never cut: the row's name (an id cut to "phanto…" names no patient)
        longest = max((len(str(v)) for v in df[key]), default=0) if key in df else 0
        table.add_column(col, no_wrap=True, min_width=max(longest, len(col)))
    table.add_column("status")
    for header, _, _ in shown:
        table.add_column(header, justify="right")
    for _, r in df.iterrows():

        def cell(key: str, fmt: str, _r: Any = r) -> str:
            v = _r.get(key)
            return "-" if v is None or v != v else fmt.format(v)

        cells = [cell(key, fmt) for _, key, fmt in shown]
        table.add_row(str(r["config"]), str(r["patient_id"]), run_status_cell(r), *cells)
    return table
