"""The ``cohort`` and ``serve`` commands: every patient of a manifest, once or on a schedule."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from tumor3d.constants import MAX_VOXELS_DEFAULT
from tumor3d.flows.cli.app import (
    CohortStore,
    DaskAddress,
    DaskWorkers,
    Layout,
    MaxVoxels,
    Verbose,
    Workers,
    _check_models,
    _load_config,
    app,
    console,
)
from tumor3d.flows.cli.errors import _HANDLED, _ctrl_c_ends, _fail
from tumor3d.flows.cli.output import _CohortReporter, print_cohort_summary
from tumor3d.flows.cli.preflight import _check_out_dir, _check_out_writable, _preflight_cohort
from tumor3d.flows.cli.session import _prefect, _reporting


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
    """Run every patient of a manifest, N at a time: OUT/<id>/, OUT/cohort.parquet/.md/.html.

    Exit code 0 when every patient succeeded with status ok, 1 when some failed
    (named in the summary; a row whose image is missing fails alone), 4 when
    none failed but some has status check (the notes say why), 2 for an invalid
    manifest or configuration, 3 for an environment error (an unwritable
    output, an unreachable Dask scheduler or object store, a Prefect server
    that cannot start).
    """
    from tumor3d.flows.cohort import check_cohort_rows, run_cohort
    from tumor3d.flows.dask_runner import DaskSpec
    from tumor3d.storage.manifest import read_manifest
    from tumor3d.storage.objectstore import is_url

    try:
        cfg = _load_config(config)
        if not is_url(out):  # an object-store URL is checked by run_cohort
            _check_out_dir(Path(out))
        rows = read_manifest(manifest, require_files=False)
        check_cohort_rows(rows, out, layout)  # a refused row: before a server starts
        _check_models(cfg, [r.modality or "t2" for r in rows if not r.segmentation])
        dask = DaskSpec(dask_address, dask_workers)
        _preflight_cohort(out, store, dask.address)  # before a Prefect server is started
        if not is_url(out):
            _check_out_writable(Path(out))
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
    from tumor3d.flows.api_use import prefect_api

    def temporary_note() -> None:
        console.print(
            "[yellow]no Prefect server configured (PREFECT_API_URL) or running (`tumor3d server "
            "start`): serving against a temporary local server, with its scheduler, that "
            "stops with this command (see README, Scheduled reprocessing).[/]"
        )

    try:
        with prefect_api(on_temporary_start=temporary_note, services=True) as api_url:
            console.print(
                f"serving deployment [bold]tumor3d-scheduled-cohort/{escape(name)}[/] "
                f"(cron {escape(cron)} {escape(timezone)}) on {escape(api_url)}; Ctrl-C to stop",
                soft_wrap=True,  # the URL in one piece, to copy
            )
            # Prefect's own hint ("prefect deployment run [DEPLOYMENT_NAME]") reaches this
            # server only from a shell that points at it, and finds `prefect` only on a PATH
            # that holds this environment's commands (a user audit: it was not)
            here = Path(sys.executable).with_name("prefect")
            prefect = str(here) if here.is_file() else "prefect"
            console.print(
                f"run it now from another shell: PREFECT_API_URL={escape(api_url)} "
                f"{escape(prefect)} deployment run 'tumor3d-scheduled-cohort/{escape(name)}'",
                soft_wrap=True,
            )
            stopped = (
                f"stopped serving tumor3d-scheduled-cohort/{escape(name)}; a run it was "
                "executing, if any, ends Crashed (set by the next tumor3d command)"
            )
            try:  # ends by Ctrl-C (Prefect's serve returns) or SIGTERM (its runner exits 0)
                serve_cohort(deployment)
            except (KeyboardInterrupt, SystemExit):
                console.print(stopped, soft_wrap=True)
                raise
            console.print(stopped, soft_wrap=True)
    except _HANDLED as exc:
        raise _fail(exc) from None
