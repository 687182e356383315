"""Single-patient flow: MR slices -> tumour masks, meshes, renders and volumes.

Wiring only. Each stage is a cached task of :mod:`tasks.stages`; this module
orders them, records which were cache hits, and publishes the results under
``<out_dir>/<patient_id>/`` as one unit: everything is written to a staging
folder which then replaces the patient folder by renames, so a failed run
leaves nothing under the final names.

Use :func:`run_patient` from Python code: it points Prefect's result storage
into the artifact store so that cached results live beside the artifacts
they refer to.
"""

from __future__ import annotations

import json
import os
import platform
import shutil
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC, datetime
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Any

import pandas as pd
from prefect import flow, get_run_logger
from prefect.settings import PREFECT_LOCAL_STORAGE_PATH, temporary_settings
from pydantic import BaseModel, ConfigDict, Field

import tumor3d
from flows.progress import ProgressEvent, report
from storage import nifti
from storage.formats import encode_parquet
from storage.inputs import input_digest
from storage.readers import derive_patient_id
from storage.store import ArtifactStore, canonical_dumps, source_grid_from_metadata
from tasks import stages
from tasks.caching import code_digest
from tasks.stages import InputSource, StageOutput
from tumor3d.config import PipelineConfig, parse_config
from tumor3d.errors import InputError
from tumor3d.scan import MODALITIES, validate_patient_id

__all__ = [
    "DirectRunner",
    "PatientResult",
    "StageRun",
    "VOLUME_LABELS",
    "VOLUME_METHODS",
    "default_store_dir",
    "patient_flow",
    "prefect_result_storage",
    "run_patient",
    "run_stages",
    "run_stages_direct",
]

#: Volume columns of metrics.parquet and the method each names.
VOLUME_METHODS: dict[str, str] = {
    "volume_eq7_mm3": "Eq. 7: (thickness + gap) x sum of tumour areas on abnormal slices",
    "volume_voxel_mm3": "voxel count of the interpolated 3-D mask x voxel volume",
    "volume_mesh_mm3": "volume enclosed by the marching-cubes mesh",
    "volume_mesh_simplified_mm3": "volume enclosed by the simplified mesh",
}

#: Short names of the volume methods, for tables.
VOLUME_LABELS: dict[str, str] = {
    "volume_eq7_mm3": "Eq. 7 (slab sum)",
    "volume_voxel_mm3": "voxel count",
    "volume_mesh_mm3": "mesh (marching cubes)",
    "volume_mesh_simplified_mm3": "mesh (simplified)",
}

_PACKAGES = (
    "prefect", "numpy", "scipy", "scikit-image", "nibabel", "pydicom", "open3d-cpu",
    "pandas", "pyarrow", "PyWavelets", "numba", "pydantic", "fast-simplification",
)  # fmt: skip


class StageRun(BaseModel):
    """How one stage went in this flow run."""

    model_config = ConfigDict(frozen=True)

    stage: str
    cached: bool
    wall_seconds: float
    compute_seconds: float
    artifacts: dict[str, str] = Field(default_factory=dict, description="name -> digest")


class PatientResult(BaseModel):
    """What :func:`patient_flow` returns: where the outputs are and the headline numbers."""

    model_config = ConfigDict(frozen=True)

    patient_id: str
    output_dir: str
    metrics: dict[str, Any]
    stages: list[StageRun]
    flow_seconds: float

    @property
    def cache_hits(self) -> list[bool]:
        """Per stage, whether it was a cache hit."""
        return [s.cached for s in self.stages]


def default_store_dir(out_dir: str | Path) -> Path:
    """The artifact store used when none is given: ``<out_dir>/.tumor3d-store``."""
    return Path(out_dir) / ".tumor3d-store"


@contextmanager
def prefect_result_storage(store_dir: str | Path) -> Iterator[None]:
    """Keep Prefect's task results (and so the cache records) inside the store."""
    path = Path(store_dir).resolve() / "prefect-results"
    path.mkdir(parents=True, exist_ok=True)
    with temporary_settings({PREFECT_LOCAL_STORAGE_PATH: path}):
        yield


class _StageRunner:
    """Runs stage tasks in order, noting cache hits and timing."""

    def __init__(self, store: ArtifactStore, patient_id: str) -> None:
        self.store = store
        self.patient_id = patient_id
        self.runs: list[StageRun] = []
        self.outputs: dict[str, StageOutput] = {}

    def run(self, stage_task: Any, **kwargs: Any) -> StageOutput:
        name = stage_task.name
        index, total = len(self.runs), len(stages.STAGES)
        report(ProgressEvent(self.patient_id, name, "started", index, total))
        t0 = time.perf_counter()
        state = stage_task(**kwargs, return_state=True)
        out: StageOutput = state.result()
        cached = state.name == "Cached"
        if cached and not all(self.store.exists(r) for r in out.artifacts.values()):
            # The cache record outlived its artifacts (store pruned by hand): recompute.
            get_run_logger().warning("%s: cached artifacts missing, recomputing", name)
            state = stage_task.with_options(refresh_cache=True)(**kwargs, return_state=True)
            out, cached = state.result(), False
        wall = time.perf_counter() - t0
        self.runs.append(
            StageRun(
                stage=name,
                cached=cached,
                wall_seconds=wall,
                compute_seconds=out.compute_seconds,
                artifacts={k: r.digest for k, r in out.artifacts.items()},
            )
        )
        self.outputs[name] = out
        report(
            ProgressEvent(
                self.patient_id, name, "cached" if cached else "done", index + 1, total, wall
            )
        )
        return out


def _prepare_source(
    input_path: str,
    *,
    patient_id: str | None,
    modality: str,
    series_uid: str | None,
    slice_thickness_mm: float | None,
    slice_gap_mm: float | None,
) -> InputSource:
    path = Path(input_path).expanduser()
    if not path.exists():
        raise InputError("no such file or folder", path=str(path))
    if modality not in MODALITIES:
        raise InputError(f"unknown modality {modality!r}: expected one of {', '.join(MODALITIES)}")
    pid = validate_patient_id(patient_id) if patient_id is not None else derive_patient_id(path)
    return InputSource(
        path=str(path.resolve()),
        name=path.name,
        digest=input_digest(path),
        modality=modality,
        patient_id=pid,
        series_uid=series_uid,
        slice_thickness_mm=slice_thickness_mm,
        slice_gap_mm=slice_gap_mm,
    )


@flow(name="tumor3d-patient", persist_result=False, log_prints=False)
def patient_flow(
    input_path: str,
    out_dir: str,
    patient_id: str | None = None,
    config: dict[str, Any] | None = None,
    modality: str = "t2",
    slice_thickness_mm: float | None = None,
    slice_gap_mm: float | None = None,
    series_uid: str | None = None,
    store_dir: str | None = None,
) -> PatientResult:
    """Reconstruct one patient's tumour and publish masks, meshes, renders and metrics.

    Parameters
    ----------
    input_path : str
        NIfTI file, DICOM series folder, or folder of 2-D slices with a YAML sidecar.
    out_dir : str
        Outputs go to ``<out_dir>/<patient_id>/``.
    patient_id : str, optional
        Folder-safe id; derived from the input's name if omitted.
    config : dict, optional
        Pipeline configuration (validated into :class:`PipelineConfig`).
    modality : {"t2", "flair", "t1c"}
    slice_thickness_mm, slice_gap_mm : float, optional
        Override what the input says about its slices.
    series_uid : str, optional
        Which DICOM series to read when a folder holds several.
    store_dir : str, optional
        Artifact store; default ``<out_dir>/.tumor3d-store``.
    """
    t_flow = time.perf_counter()
    cfg = parse_config(config or {}, source="config")
    source = _prepare_source(
        input_path,
        patient_id=patient_id,
        modality=modality,
        series_uid=series_uid,
        slice_thickness_mm=slice_thickness_mm,
        slice_gap_mm=slice_gap_mm,
    )
    pid = source.patient_id
    store = ArtifactStore(store_dir or default_store_dir(out_dir))
    root = str(store.root)
    logger = get_run_logger()
    logger.info("patient %s: %s", pid, source.name)

    run = _StageRunner(store, pid)
    run_stages(run, source, cfg, root)
    flow_seconds = time.perf_counter() - t_flow
    metrics = _metrics_row(run, pid, flow_seconds)
    out_path = _publish(store, Path(out_dir), pid, run, metrics, cfg, source)
    logger.info("patient %s: published %s", pid, out_path)
    return PatientResult(
        patient_id=pid,
        output_dir=str(out_path),
        metrics=metrics,
        stages=run.runs,
        flow_seconds=flow_seconds,
    )


def run_stages(run: Any, source: InputSource, cfg: PipelineConfig, root: str) -> None:
    """The pipeline's wiring: every stage in order, each fed its inputs' references.

    ``run`` is a runner whose ``run(task, **kwargs)`` executes one stage and
    returns its :class:`StageOutput`: :class:`_StageRunner` runs the Prefect
    tasks (cached); :class:`DirectRunner` calls their functions directly.
    """
    scan = run.run(stages.ingest_task, source=source, store_root=root).artifacts["scan"]
    pre = run.run(stages.preprocess_task, scan=scan, config=cfg.preprocess, store_root=root)
    enhanced, brain = pre.artifacts["enhanced"], pre.artifacts["brain_mask"]
    det = run.run(
        stages.detect_task, enhanced=enhanced, brain_mask=brain, config=cfg.detect, store_root=root
    ).artifacts["detection"]
    seg = run.run(
        stages.segment_task,
        scan=scan,
        enhanced=enhanced,
        brain_mask=brain,
        detection=det,
        config=cfg.segment,
        store_root=root,
    )
    itp = run.run(
        stages.interpolate_task,
        scan=scan,
        tumor_mask_slices=seg.artifacts["tumor_mask_slices"],
        config=cfg.interpolate,
        store_root=root,
    )
    surface = run.run(
        stages.surface_task,
        tumor_mask=itp.artifacts["tumor_mask"],
        config=cfg.surface,
        store_root=root,
    )
    simple = run.run(
        stages.simplify_task, mesh=surface.artifacts["mesh"], config=cfg.simplify, store_root=root
    )
    run.run(stages.render_task, mesh=simple.artifacts["mesh"], config=cfg.render, store_root=root)
    run.run(
        stages.measure_task,
        scan=scan,
        detection=det,
        segmentation=seg.artifacts["segmentation"],
        tumor_mask=itp.artifacts["tumor_mask"],
        mesh=surface.artifacts["mesh"],
        mesh_simplified=simple.artifacts["mesh"],
        store_root=root,
    )


class DirectRunner:
    """Runs each stage's function directly, without Prefect (no caching).

    For benchmarks (the peer of the flow) and in-process evaluation.
    ``outputs`` maps stage name to :class:`StageOutput`, ``seconds`` to its
    wall time.
    """

    def __init__(self) -> None:
        self.outputs: dict[str, StageOutput] = {}
        self.seconds: dict[str, float] = {}

    def run(self, stage_task: Any, **kwargs: Any) -> StageOutput:
        """Call the stage's undecorated function and time it."""
        t0 = time.perf_counter()
        out = stage_task.fn(**kwargs)
        self.seconds[stage_task.name] = time.perf_counter() - t0
        self.outputs[stage_task.name] = out
        return out


def run_stages_direct(
    input_path: str | Path,
    store_dir: str | Path,
    *,
    config: dict[str, Any] | PipelineConfig | None = None,
    patient_id: str | None = None,
    modality: str = "t2",
) -> DirectRunner:
    """Run every stage in this process without Prefect; artifacts go to ``store_dir``."""
    cfg = config if isinstance(config, PipelineConfig) else parse_config(config or {})
    source = _prepare_source(
        str(input_path),
        patient_id=patient_id,
        modality=modality,
        series_uid=None,
        slice_thickness_mm=None,
        slice_gap_mm=None,
    )
    runner = DirectRunner()
    run_stages(runner, source, cfg, str(ArtifactStore(store_dir).root))
    return runner


def run_patient(input_path: str | Path, out_dir: str | Path, **kwargs: Any) -> PatientResult:
    """Run :func:`patient_flow` with Prefect's results kept in the artifact store.

    Keyword arguments are those of :func:`patient_flow`.
    """
    store_dir = kwargs.pop("store_dir", None) or default_store_dir(out_dir)
    with prefect_result_storage(store_dir):
        return patient_flow(str(input_path), str(out_dir), store_dir=str(store_dir), **kwargs)


def _metrics_row(run: _StageRunner, pid: str, flow_seconds: float) -> dict[str, Any]:
    vol = run.outputs["measure-volume"].values
    row: dict[str, Any] = {"patient_id": pid}
    row.update(vol)
    row["faces_mc"] = int(run.outputs["extract-surface"].values["faces"])
    row["faces_simplified"] = int(run.outputs["simplify-mesh"].values["faces"])
    row["faces_target"] = int(run.outputs["simplify-mesh"].values["faces_target"])
    row["mesh_watertight"] = bool(run.outputs["extract-surface"].values["watertight"])
    row["mesh_simplified_watertight"] = bool(run.outputs["simplify-mesh"].values["watertight"])
    row["slices_between"] = int(run.outputs["interpolate-slices"].values["slices_between"])
    for r in run.runs:
        key = r.stage.replace("-", "_")
        row[f"time_{key}_s"] = float(r.compute_seconds)
        row[f"cached_{key}"] = bool(r.cached)
    row["time_flow_s"] = float(flow_seconds)
    return row


def _versions() -> dict[str, str]:
    out = {"tumor3d": tumor3d.__version__, "python": platform.python_version()}
    for name in _PACKAGES:
        try:
            out[name] = importlib_metadata.version(name)
        except importlib_metadata.PackageNotFoundError:
            out[name] = "not installed"
    return out


def _slice_table(store: ArtifactStore, run: _StageRunner) -> pd.DataFrame:
    det = store.get_table(run.outputs["detect-abnormal"].artifacts["detection"])
    seg = store.get_table(run.outputs["segment-tumor"].artifacts["segmentation"])
    table = det.merge(seg, on="slice_index", how="left")
    area = run.outputs["measure-volume"].values["pixel_area_mm2"]
    table["tumor_area_mm2"] = table["tumor_pixels"].fillna(0) * area
    return table


def _publish(
    store: ArtifactStore,
    out_dir: Path,
    pid: str,
    run: _StageRunner,
    metrics: dict[str, Any],
    cfg: PipelineConfig,
    source: InputSource,
) -> Path:
    """Write the patient's outputs to a staging folder, then swap it into place."""
    out_dir.mkdir(parents=True, exist_ok=True)
    final = out_dir / pid
    staging = out_dir / f".{pid}.partial-{uuid.uuid4().hex[:8]}"
    staging.mkdir()
    try:
        scan_ref = run.outputs["ingest-scan"].artifacts["scan"]
        grid = source_grid_from_metadata(scan_ref.metadata)
        seg = run.outputs["segment-tumor"].artifacts
        slices_mask, _ = store.get_volume(seg["tumor_mask_slices"])
        (staging / "tumor_mask_slices.nii.gz").write_bytes(
            nifti.mask_to_source_nifti_bytes(slices_mask, grid)
        )
        brain, _ = store.get_volume(run.outputs["preprocess"].artifacts["brain_mask"])
        (staging / "brain_mask.nii.gz").write_bytes(nifti.mask_to_source_nifti_bytes(brain, grid))
        fine, fine_affine = store.get_volume(
            run.outputs["interpolate-slices"].artifacts["tumor_mask"]
        )
        (staging / "tumor_mask.nii.gz").write_bytes(
            nifti.volume_to_source_nifti_bytes(fine, fine_affine, grid, dtype="uint8")
        )
        (staging / "tumor.ply").write_bytes(
            store.get_bytes(run.outputs["extract-surface"].artifacts["mesh"])
        )
        (staging / "tumor_simplified.ply").write_bytes(
            store.get_bytes(run.outputs["simplify-mesh"].artifacts["mesh"])
        )
        for name, ref in run.outputs["render-views"].artifacts.items():
            (staging / f"{name}{Path(ref.relpath).suffix}").write_bytes(store.get_bytes(ref))
        (staging / "slices.parquet").write_bytes(encode_parquet(_slice_table(store, run)))
        (staging / "metrics.parquet").write_bytes(encode_parquet(pd.DataFrame([metrics])))
        provenance = {
            "created_utc": datetime.now(UTC).isoformat(timespec="seconds"),
            "method": "Arakeri & Reddy (2013), IJSIP 6(3); see ALGORITHMS.md choices [A1]-[A29]",
            "versions": _versions(),
            "input": {
                "name": source.name,
                "digest_sha256": source.digest,
                "modality": source.modality,
                "patient_id": pid,
            },  # fmt: skip
            "config": json.loads(canonical_dumps(cfg.model_dump(mode="json"))),
            "volume_methods": VOLUME_METHODS,
            "stages": [
                {**r.model_dump(), "code_sha256": code_digest(stages.stage_modules(r.stage))}
                for r in run.runs
            ],
        }
        (staging / "provenance.json").write_text(json.dumps(provenance, indent=2) + "\n")
        for f in staging.iterdir():
            with open(f, "rb") as fh:
                os.fsync(fh.fileno())
        _swap_into_place(staging, final)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return final


def _swap_into_place(staging: Path, final: Path) -> None:
    """Replace ``final`` by ``staging`` with renames; restore the old one on failure."""
    trash = final.with_name(f".{final.name}.old-{uuid.uuid4().hex[:8]}")
    had_old = final.exists()
    if had_old:
        os.replace(final, trash)
    try:
        os.replace(staging, final)
    except BaseException:
        if had_old:
            os.replace(trash, final)
        raise
    if had_old:
        shutil.rmtree(trash, ignore_errors=True)
