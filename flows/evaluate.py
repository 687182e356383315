"""Evaluation flow: run a cohort and compare every patient with its reference.

``tumor3d evaluate MANIFEST... --out DIR [--config NAME=FILE ...]`` runs
:func:`evaluate_flow`:

1. read the manifest(s) leniently (:func:`tumor3d.storage.evaluation_tables.collect_rows`):
   a bad row is reported and skipped, the others go on; a row whose file is
   absent is *skipped* (not a failure);
2. prepare each row (:func:`tumor3d.storage.evaluation_io.prepare_case`): check the
   reference (readable, in the image's world space, holding the requested
   labels) and, for rows with ``emulate_step_mm``, write the emulated
   thick-slice image under ``DIR/emulated/<patient_id>/``;
3. for every configuration, run the cohort into ``DIR/runs/<config>/``
   (one artifact store ``DIR/.tumor3d-store`` shared by all configurations,
   so a re-run, or a stage configured alike, is a cache hit);
4. compare each published patient with its reference by every registered
   evaluation (:func:`tumor3d.evaluation.selected_evaluations`: the default
   ones, or those named with ``--evaluation``) into rows
   (:func:`tumor3d.storage.evaluation_tables.evaluation_rows`);
5. write ``DIR/evaluation.parquet`` (one row per configuration and patient),
   ``DIR/evaluation_slices.parquet`` (per acquired slice)
   (:func:`tumor3d.storage.evaluation_tables.write_evaluation_tables`), the Bland-Altman
   plots and ``DIR/REPORT.md`` (:mod:`tumor3d.storage.evaluation_report`).

The patients run through :func:`tumor3d.flows.cohort.run_cohort` (the cohort flow:
``--workers`` patients at a time, failures isolated per patient).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pandas as pd
from prefect import flow, get_run_logger

from tumor3d.config import parse_config
from tumor3d.errors import InputError
from tumor3d.evaluation import selected_evaluations
from tumor3d.storage.evaluation_tables import (
    collect_rows,
    evaluation_rows,
    prepare_cases,
    write_evaluation_tables,
)
from tumor3d.storage.given_models import read_config_file
from tumor3d.storage.objectstore import default_store_location
from tumor3d.tasks.publish import REVIEW_COLUMNS

__all__ = [
    "EvaluationResult",
    "evaluate_flow",
    "parse_config_specs",
    "run_evaluation",
]


@dataclass
class EvaluationResult:
    """What the evaluation flow returns.

    ``patients`` / ``slices``: the tables written as ``evaluation.parquet``
    and ``evaluation_slices.parquet``; ``skipped``: rows not evaluated
    (patient id or row, reason, whether only a file was absent); ``report``:
    the path of ``REPORT.md``.
    """

    out_dir: Path
    patients: pd.DataFrame
    slices: pd.DataFrame
    skipped: list[dict[str, Any]] = field(default_factory=list)
    report: Path | None = None

    @property
    def n_failed(self) -> int:
        """Patients (over all configurations) whose pipeline run failed."""
        return int((self.patients["status"] == "failed").sum()) if len(self.patients) else 0

    @property
    def n_invalid(self) -> int:
        """Manifest rows rejected for a reason other than an absent file."""
        return sum(1 for s in self.skipped if not s["missing_file"])


def parse_config_specs(specs: Sequence[str] | None) -> dict[str, str | None]:
    """Parse ``--config`` values: ``NAME=FILE`` or ``FILE`` (name = file stem).

    Returns an ordered mapping name -> file (``{"default": None}`` when none given).

    Raises
    ------
    InputError
        An empty or unsafe name, or a name given twice.
    """
    out: dict[str, str | None] = {}
    for spec in specs or []:
        if "=" in spec:
            name, _, path = spec.partition("=")
        else:
            path = spec
            name = Path(spec).name.split(".")[0]
        name, path = name.strip(), path.strip()
        if not name or not name.replace("-", "").replace("_", "").isalnum() or not path:
            raise InputError(
                f"bad --config {spec!r}: expected NAME=FILE with a name of letters, digits, "
                "'-' and '_'"
            )
        if name in out:
            raise InputError(f"--config name {name!r} is given twice")
        out[name] = path
    return out or {"default": None}


def _load_configs(specs: dict[str, str | None]) -> dict[str, dict[str, Any]]:
    configs = {}
    for name, path in specs.items():
        if path is None:
            configs[name] = parse_config({}).model_dump(mode="json")
            continue
        configs[name] = read_config_file(path).model_dump(mode="json")
    return configs


# --------------------------------------------------------------------------- cohort


def _run_cohort(rows, out_dir, *, config, workers, store_dir) -> Any:
    from tumor3d.flows.cohort import run_cohort

    return run_cohort(rows, out_dir, config=config, workers=workers, store_dir=store_dir)


# --------------------------------------------------------------------------- flow


def _evaluate_run_name() -> str:
    from prefect.runtime import flow_run

    return f"evaluate-{Path(str(flow_run.parameters.get('out_dir', 'eval'))).name}"


@flow(
    name="tumor3d-evaluate", flow_run_name=_evaluate_run_name, persist_result=False,
    log_prints=False,
)  # fmt: skip
def evaluate_flow(
    manifests: list[str],
    out_dir: str,
    config_files: dict[str, str | None] | None = None,
    workers: int | None = None,
    store_dir: str | None = None,
    phantoms: int = 0,
    command: str | None = None,
    evaluations: list[str] | None = None,
) -> EvaluationResult:
    """Run the cohort for each configuration and evaluate it against the references.

    Parameters
    ----------
    manifests : list of str
        Cohort manifest CSV files (their rows are concatenated; patient ids
        must be unique over all of them).
    out_dir : str
        Output folder (see the module docstring for its layout).
    config_files : dict, optional
        Configuration name -> YAML file (``None`` = the defaults); default
        ``{"default": None}``.
    workers : int, optional
        Patients run at a time (passed to the cohort runner).
    store_dir : str, optional
        Artifact store; default ``<out_dir>/.tumor3d-store``.
    phantoms : int, default 0
        Also generate this many phantom patients (seeds 0..N-1, their truth
        as reference) under ``<out_dir>/phantoms/``.
    command : str, optional
        The command line, for the report.
    evaluations : list of str, optional
        Registered evaluations to run (:func:`tumor3d.evaluation.
        selected_evaluations`); default the default ones (``segmentation``).
    """
    from tumor3d.storage.evaluation_report import write_report

    t0 = time.perf_counter()
    logger = get_run_logger()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    store = Path(store_dir) if store_dir else default_store_location(out)
    configs = _load_configs(config_files or {"default": None})
    chosen = selected_evaluations(evaluations)  # an unknown name: before any work

    rows, skipped = collect_rows(manifests, phantoms, out / "phantoms")
    prepared, refused = prepare_cases(rows, out / "emulated")
    skipped += refused
    for s in skipped:
        logger.warning("skipped: %s", s["reason"])

    patient_rows: list[dict[str, Any]] = []
    slice_rows: list[dict[str, Any]] = []
    for cname, cfg in configs.items():
        result = _run_cohort(
            [p.run_row for p in prepared], out / "runs" / cname, config=cfg, workers=workers,
            store_dir=store,
        )  # fmt: skip
        got = evaluation_rows(cname, prepared, result.patients, chosen,
                              review_columns=REVIEW_COLUMNS)  # fmt: skip
        patient_rows += got[0]
        slice_rows += got[1]

    patients, slices = write_evaluation_tables(out, patient_rows, slice_rows)
    res = EvaluationResult(out, patients, slices, skipped)
    res.report = write_report(
        out, patients, slices,
        configs=configs, config_files=config_files or {"default": None},
        prepared=prepared, skipped=skipped, evaluations=chosen,
        command=command, elapsed_s=time.perf_counter() - t0,
    )  # fmt: skip
    return res


def run_evaluation(
    manifests: str | Path | Sequence[str | Path],
    out_dir: str | Path,
    *,
    config_files: dict[str, str | None] | None = None,
    workers: int | None = None,
    store_dir: str | Path | None = None,
    phantoms: int = 0,
    command: str | None = None,
    evaluations: Sequence[str] | None = None,
) -> EvaluationResult:
    """Run :func:`evaluate_flow` (arguments as there) from Python code.

    ``manifests``: one manifest's path, or a list of them. Against the Prefect API
    :func:`tumor3d.flows.api_use.api_of_python_call` picks.
    """
    from tumor3d.flows.api_use import api_of_python_call

    paths = [manifests] if isinstance(manifests, str | Path) else list(manifests)
    with api_of_python_call():
        return evaluate_flow(
            [str(m) for m in paths], str(out_dir), config_files=config_files,
            workers=workers, store_dir=None if store_dir is None else str(store_dir),
            phantoms=phantoms, command=command,
            evaluations=None if evaluations is None else list(evaluations),
        )  # fmt: skip
