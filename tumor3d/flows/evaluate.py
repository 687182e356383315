"""Evaluation flow: run a cohort and compare every patient with its reference.

``tumor3d evaluate MANIFEST... --out DIR [--config NAME=FILE ...]`` runs
:func:`evaluate_flow`:

1. read the manifest(s) leniently (:func:`tumor3d.storage.manifest.read_manifest_rows`):
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
   ones, or those named with ``--evaluation``);
5. write ``DIR/evaluation.parquet`` (one row per configuration and patient),
   ``DIR/evaluation_slices.parquet`` (per acquired slice), the Bland-Altman
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

import numpy as np
import pandas as pd
from prefect import flow, get_run_logger

from tumor3d.config import parse_config
from tumor3d.errors import InputError
from tumor3d.evaluation import selected_evaluations
from tumor3d.storage.evaluation_io import PreparedCase, load_case, prepare_case
from tumor3d.storage.formats import encode_parquet
from tumor3d.storage.manifest import ManifestRow, RowProblem, read_manifest_rows
from tumor3d.storage.objectstore import default_store_location
from tumor3d.storage.store import atomic_write_bytes
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
        p = Path(path)
        try:
            text = p.read_text()
        except OSError as exc:
            raise InputError(f"cannot read configuration: {exc.strerror}", str(p)) from None
        configs[name] = parse_config(text, source=str(p)).model_dump(mode="json")
    return configs


# --------------------------------------------------------------------------- cohort


def _run_cohort(rows, out_dir, *, config, workers, store_dir) -> Any:
    from tumor3d.flows.cohort import run_cohort

    return run_cohort(rows, out_dir, config=config, workers=workers, store_dir=store_dir)


# --------------------------------------------------------------------------- flow


def _phantom_rows(n: int, folder: Path) -> list[ManifestRow]:
    from dataclasses import replace

    from tumor3d.phantom import make_phantom_patient
    from tumor3d.storage.phantom_io import write_phantom_cohort

    patients = [make_phantom_patient(seed, patient_id=f"phantom{seed:03d}") for seed in range(n)]
    manifest = write_phantom_cohort(patients, folder)
    rows, problems = read_manifest_rows(manifest)
    if problems:  # pragma: no cover - we wrote it ourselves
        raise InputError(problems[0].message)
    return [replace(r, reference_kind="truth") for r in rows]


def _group(prepared: PreparedCase) -> str:
    return f"{prepared.reference_kind}, {prepared.acquisition}"


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

    rows: list[ManifestRow] = []
    skipped: list[dict[str, Any]] = []
    seen: dict[str, str] = {}
    sources: list[tuple[str, list[ManifestRow]]] = []
    for m in manifests:
        good, problems = read_manifest_rows(m)
        sources.append((str(m), good))
        for q in problems:
            skipped.append(_skip(q.patient_id, q.message, q.missing_file, q))
    if phantoms:
        generated = _phantom_rows(phantoms, out / "phantoms")
        sources.append((f"{phantoms} generated phantoms", generated))
    for where, good in sources:
        for r in good:
            if r.patient_id in seen:
                pid = r.patient_id
                why = f"{where}: duplicate patient_id {pid!r} (also in {seen[pid]})"
                skipped.append(_skip(r.patient_id, why, False))
                continue
            seen[r.patient_id] = where
            rows.append(r)

    prepared: list[PreparedCase] = []
    for r in rows:
        try:
            prepared.append(prepare_case(r, out / "emulated"))
        except InputError as exc:
            skipped.append(_skip(r.patient_id, str(exc), False))
    for s in skipped:
        logger.warning("skipped: %s", s["reason"])

    patient_rows: list[dict[str, Any]] = []
    slice_rows: list[dict[str, Any]] = []
    for cname, cfg in configs.items():
        run_dir = out / "runs" / cname
        result = _run_cohort(
            [p.run_row for p in prepared], run_dir, config=cfg, workers=workers, store_dir=store
        )
        by_id = {o.patient_id: o for o in result.patients}
        for p in prepared:
            pid = p.source.patient_id
            o = by_id.get(pid)
            base = {
                "config": cname, "patient_id": pid, "group": _group(p),
                "reference_kind": p.reference_kind, "acquisition": p.acquisition,
                "modality": p.source.modality, "image": p.source.image.name,
                # evaluated or not; the run's own ok/check is run_status
                "status": "failed" if o is None or o.status == "failed" else "ok",
                "run_status": "failed" if o is None else o.status,
                "failed_stage": None if o is None else o.failed_stage,
                "error": "not run" if o is None else o.error,
            }  # fmt: skip
            if o is None or o.status == "failed":
                patient_rows.append(base)
                continue
            base.update({k: v for k, v in o.metrics.items() if k.startswith(("volume_", "n_"))})
            base["notes"] = str(o.metrics.get("notes") or "")
            # when to check, as the run published it (metrics.parquet's columns)
            for key in REVIEW_COLUMNS:
                if key in o.metrics:
                    base[key] = o.metrics[key]
            try:
                case = load_case(p, o.output_dir)
                for ev in chosen.values():
                    got = ev.fn(case)
                    base.update(got.patient)
                    for srow in got.slices:
                        slice_rows.append({"config": cname, "patient_id": pid,
                                           "evaluation": ev.name, **srow})  # fmt: skip
            except Exception as exc:  # one patient's comparison must not stop the others
                base.update(status="failed", failed_stage="evaluate",
                            error=f"{type(exc).__name__}: {exc}".splitlines()[0])  # fmt: skip
            patient_rows.append(base)

    patients = pd.DataFrame(patient_rows)
    slices = pd.DataFrame(slice_rows)
    atomic_write_bytes(out / "evaluation.parquet", encode_parquet(_parquet_safe(patients)))
    atomic_write_bytes(out / "evaluation_slices.parquet", encode_parquet(_parquet_safe(slices)))
    res = EvaluationResult(out, patients, slices, skipped)
    res.report = write_report(
        out, patients, slices,
        configs=configs, config_files=config_files or {"default": None},
        prepared=prepared, skipped=skipped, evaluations=chosen,
        command=command, elapsed_s=time.perf_counter() - t0,
    )  # fmt: skip
    return res


def _skip(pid: str | None, reason: str, missing: bool, problem: RowProblem | None = None) -> dict:
    return {
        "patient_id": pid,
        "row": None if problem is None else problem.row,
        "reason": reason,
        "missing_file": bool(missing),
    }


def _parquet_safe(df: pd.DataFrame) -> pd.DataFrame:
    """Object columns holding mixed None/bool/number become parquet-friendly."""
    out = df.copy()
    for c in out.columns:
        if out[c].dtype == object:
            values = [v for v in out[c] if v is not None and not _is_nan(v)]
            if values and all(isinstance(v, bool | np.bool_) for v in values):
                out[c] = out[c].astype("boolean")
            elif values and all(isinstance(v, int | float | np.number) for v in values):
                out[c] = pd.to_numeric(out[c], errors="coerce")
            else:
                out[c] = out[c].map(lambda v: None if v is None else str(v))
    return out


def _is_nan(v: Any) -> bool:
    return isinstance(v, float) and np.isnan(v)


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
