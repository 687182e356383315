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
  status ``check``: the tool's own checks doubt it (a segmentation caveat but
  the midline one, a
  brain mask that makes the volume unreliable, skipped files, a segmentation
  that asks for review); the summary says why (:data:`EXIT_CHECK`,
  :mod:`tumor3d.segmentation.review`). A cohort with failures exits 1.

User-supplied strings are escaped before Rich prints them. When stdout is not
a terminal, progress is one plain line per stage instead of a progress bar.

The package: the ``run`` command here (it looks ``_run_with_progress`` and
``print_summary`` up in this namespace), the other commands in
:mod:`~tumor3d.flows.cli.cohort` (``cohort``, ``serve``), :mod:`~tumor3d.flows.cli.demo`
(``demo``, ``phantom``), :mod:`~tumor3d.flows.cli.server`, :mod:`~tumor3d.flows.cli.methods`,
:mod:`~tumor3d.flows.cli.evaluate` and :mod:`~tumor3d.flows.cli.train`; what they share in
:mod:`~tumor3d.flows.cli.app` (the application, shared options, configuration),
:mod:`~tumor3d.flows.cli.errors` (exit codes, one-line errors, Ctrl-C),
:mod:`~tumor3d.flows.cli.session` (the Prefect session), :mod:`~tumor3d.flows.cli.output`
(progress and summaries), :mod:`~tumor3d.flows.cli.preflight` (checks before a run) and
:mod:`~tumor3d.flows.cli.process` (running a command to its end).
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
from typing import Annotated  # noqa: E402

import typer  # noqa: E402

from tumor3d.constants import MAX_VOXELS_DEFAULT  # noqa: E402

# F401: names the daemon, other modules and tests import from here
from tumor3d.flows.cli.app import (  # noqa: E402, F401
    CohortStore,
    Layout,
    MaxVoxels,
    Verbose,
    _check_models,
    _load_config,
    app,
    console,
    err_console,
)
from tumor3d.flows.cli.errors import (  # noqa: E402, F401
    _HANDLED,
    EXIT_CHECK,
    EXIT_ENVIRONMENT,
    EXIT_INPUT,
    EXIT_INTERRUPTED,
    _error_line,
    _fail,
)
from tumor3d.flows.cli.output import (  # noqa: E402, F401
    _patient_exit_code,
    print_cohort_summary,
    print_summary,
)
from tumor3d.flows.cli.preflight import (  # noqa: E402
    _location,
    _preflight,
    _say_derived_id,
    _say_modality,
)
from tumor3d.flows.cli.process import finish_process, main, run_command  # noqa: E402, F401
from tumor3d.flows.cli.session import (  # noqa: E402, F401
    _no_heartbeats,
    _run_with_progress,
)


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
        typer.Option(
            help="t2, flair or t1c (default: what a slice folder's stack.yaml names, else t2; "
            "said on the console)."
        ),
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
    from tumor3d.storage.readers import resolve_modality
    from tumor3d.storage.readers.handoff import forget_kept
    from tumor3d.storage.readers.options import ReadOptions

    try:
        cfg = _load_config(config)
        # the option, else what an image stack's sidecar names, else the default (said)
        modality, origin = resolve_modality(input_path, modality)
        # the folder holds the scan's model, if it is used (not with a given segmentation)
        _check_models(cfg, [] if segmentation is not None else [modality])
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
            # a default modality passed as none: the flow takes the same and says so in
            # the run's notes (report, metrics), not only on this console
            **{**options.model_dump(), "modality": None if origin == "default" else modality},
        )
    except _HANDLED as exc:
        raise _fail(exc) from None
    finally:
        forget_kept()  # a scan the ingest stage did not need (its result was cached)
    _say_modality(modality, origin, input_path)
    if patient_id is None:
        _say_derived_id(input_path)
    print_summary(result)
    raise typer.Exit(code=_patient_exit_code(result))


# The commands register in this order after run, and --help lists them so.
# isort: off
import tumor3d.flows.cli.cohort  # noqa: E402, F401
import tumor3d.flows.cli.demo  # noqa: E402, F401
import tumor3d.flows.cli.server  # noqa: E402, F401
import tumor3d.flows.cli.methods  # noqa: E402, F401
import tumor3d.flows.cli.evaluate  # noqa: E402, F401
import tumor3d.flows.cli.train  # noqa: E402, F401
# isort: on
