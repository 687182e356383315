"""Training flow: the learned segmentation's models from a manifest of labelled patients.

``tumor3d train MANIFEST --out DIR`` (:func:`run_training`). For every row
(a cohort manifest with a ``reference`` column, or ``reference_kind``
``tumor_free``; ``emulate_step_mm`` rows are emulated as the evaluation
does, :func:`tumor3d.storage.evaluation_io.prepare_case`):

1. the pipeline's ingest-scan, preprocess and detect-abnormal stages (the
   same cached Prefect tasks as ``run`` and ``cohort``: a store shared with
   a cohort run reuses them);
2. the training-rows stage (:mod:`tumor3d.tasks.train`), cached by content like
   every stage: the reference on the acquired slices, the features with the
   robust method's mask as the prior, the sampled rows;

then one model per family (FLAIR + T2 ``hyper``, T1c ``t1c``) present in
the manifest is trained on its patients' rows (LightGBM, the ``train``
extra) and written as ``DIR/<family>.npz`` (plain arrays, no pickle) with
``DIR/training.json`` (the cases, their input digests, the parameters and
the model digests). A model is used by shipping it: copied over
``tumor3d/learned/models/<family>.npz``, whose bytes are in the
segment-tumor stage's cache key.

With ``--cnn`` (``cnn=True``) the FLAIR patients also train the U-Net of
:mod:`tumor3d.learned.cnn` (PyTorch, the ``train`` extra): the unet-slices
stage (:data:`tumor3d.tasks.train.UNET_SLICES`, cached like the rows) gives
each FLAIR patient's input and target slices, one network is trained on all
of them (:func:`tumor3d.learned.cnn_train.train_unet`, the shipped settings
unless ``cnn_settings`` says otherwise) once per seed of ``cnn_seeds`` (the
shipped ensemble: seeds 0 and 1), each written as ``DIR/unet_flair_seed<s>.npz``
(plain arrays; ``meta_json`` names the cases, the settings and the seed),
listed in ``training.json`` beside the forests. The shipped ensemble reads
seeds 0 and 1 (:data:`tumor3d.learned.shipped.CNN_MODELS`): they are shipped by
copying them over ``tumor3d/learned/models/unet_flair_seed{0,1}.npz``.
"""

from __future__ import annotations

import dataclasses
import datetime
import json
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from prefect import flow, get_run_logger

from tumor3d.config import PipelineConfig, parse_config
from tumor3d.errors import InputError
from tumor3d.flows.patient import prepare_brain_mask, prepare_source
from tumor3d.learned.cnn_train import UNetSettings, require_torch, slices_from_bytes, train_unet
from tumor3d.learned.rows import rows_from_bytes
from tumor3d.learned.shipped import MODEL_FAMILIES
from tumor3d.learned.training import NUM_ROUNDS, TrainingRows, train_forest
from tumor3d.storage.atomic import atomic_write_bytes
from tumor3d.storage.evaluation_io import acquired_reference, prepare_case
from tumor3d.storage.manifest import ManifestRow, read_manifest
from tumor3d.storage.objectstore import default_store_location, open_store
from tumor3d.storage.store import ArtifactStore
from tumor3d.tasks import stages
from tumor3d.tasks.runner import PrefectRunner
from tumor3d.tasks.train import SPEC as TRAINING_ROWS
from tumor3d.tasks.train import UNET_SLICES

__all__ = ["TrainResult", "run_training", "train_flow"]

#: The pipeline's stages the training stages take their inputs from (shared with run and
#: cohort): ingest-scan, preprocess and detect-abnormal, read from the declarations.
_PIPELINE_STAGES = stages.upstream(TRAINING_ROWS, UNET_SLICES)
# the order the flow runs them in feeds every declared input (once, at import)
stages.check_wiring([*_PIPELINE_STAGES, TRAINING_ROWS, UNET_SLICES])
#: Modalities the U-Net is trained on (its cross-validation: FLAIR; the file's name says so).
UNET_MODALITIES = ("flair",)
#: Settings of ``cnn_settings`` the unet-slices stage fixes (its slices are the shipped grid).
_UNET_GRID = ("size", "context", "framing")


@dataclass
class TrainResult:
    """What a training run wrote and from what."""

    out_dir: str
    models: dict[str, str] = field(default_factory=dict)  # family -> model file
    cases: list[dict[str, Any]] = field(default_factory=list)
    cached_patients: int = 0


def _check_rows(rows: list[ManifestRow], where: str) -> None:
    for i, r in enumerate(rows, start=1):
        if r.reference is None and r.reference_kind != "tumor_free":
            raise InputError(
                f"manifest row {i} ({r.patient_id}): training needs a reference "
                "(column reference, or reference_kind tumor_free)",
                where,
            )
        if r.segmentation is not None:
            raise InputError(
                f"manifest row {i} ({r.patient_id}): a segmentation column has no use in "
                "training (the reference is the label)",
                where,
            )


def _patient_rows(
    row: ManifestRow, cfg: PipelineConfig, store: ArtifactStore, work_dir: Path, cnn: bool = False
) -> tuple[TrainingRows, dict[str, Any], tuple[np.ndarray, np.ndarray] | None]:
    """One patient through the cached stages; its rows, a description, its U-Net slices.

    The slices (``(x, y)``, :data:`UNET_SLICES`) only with ``cnn`` and a FLAIR patient.
    """
    unet = cnn and row.modality in UNET_MODALITIES
    prepared = prepare_case(row, work_dir)
    run_row = prepared.run_row
    source = prepare_source(
        run_row.image, patient_id=row.patient_id, modality=row.modality,
        slice_thickness_mm=run_row.slice_thickness_mm, slice_gap_mm=run_row.slice_gap_mm,
    )  # fmt: skip
    mask = None
    if run_row.brain_mask is not None:
        mask = prepare_brain_mask(run_row.brain_mask, source)
    given = stages.store_given(store, brain_mask=mask)
    root = str(store.root)
    runner = PrefectRunner(store, row.patient_id, len(_PIPELINE_STAGES) + 1 + int(unet))
    for spec in _PIPELINE_STAGES:  # wired from their declarations, as run_stages does
        inputs = stages.stage_inputs(spec, runner.outputs, source=source, cfg=cfg, given=given)
        runner.run(spec, **inputs, store_root=root)
    scan = stages.product(runner.outputs, TRAINING_ROWS.inputs["scan"])  # the rows' scan
    if row.reference is not None:
        ref, ref_affine = acquired_reference(prepared)
        meta = {"tumor_free": False}
    else:  # tumor_free: an empty label on the scan's grid
        shape = tuple(scan.metadata["shape_zyx"])[::-1]
        ref, ref_affine = np.zeros(shape, bool), np.asarray(scan.metadata["affine"])
        meta = {"tumor_free": True}
    # the reference in file order with its affine: stored as (z, y, x) = its transpose
    ref_art = store.put_volume(ref.transpose(2, 1, 0), ref_affine, kind="mask", extra=meta)
    inputs = stages.stage_inputs(
        TRAINING_ROWS, runner.outputs, cfg=cfg, given={"reference": ref_art}
    )
    out = runner.run(TRAINING_ROWS, **inputs, store_root=root)
    ref_rows = out.artifacts["rows"]
    rows = rows_from_bytes(store.get_bytes(ref_rows), source=f"{row.patient_id} training rows")
    case = {
        "patient_id": row.patient_id,
        "modality": row.modality,
        "image": run_row.image.name if row.emulate_step_mm is None else row.image.name,
        "image_sha256": source.digest,
        "acquisition": prepared.acquisition,
        "reference_kind": prepared.reference_kind,
        "rows": int(out.values["n_rows"]),
        "lesion_rows": int(out.values["n_lesion_rows"]),
        "rows_digest": ref_rows.digest,
    }
    slices = None
    if unet:
        inputs = stages.stage_inputs(
            UNET_SLICES, runner.outputs, cfg=cfg, given={"reference": ref_art}
        )
        out = runner.run(UNET_SLICES, **inputs, store_root=root)
        ref_slices = out.artifacts["slices"]
        slices = slices_from_bytes(
            store.get_bytes(ref_slices), source=f"{row.patient_id} U-Net slices"
        )
        case["unet_slices"] = int(out.values["n_slices"])
        case["unet_tumour_slices"] = int(out.values["n_tumour_slices"])
        case["unet_slices_digest"] = ref_slices.digest
    case["cached"] = all(r.cached for r in runner.runs)
    return rows, case, slices


def _train_run_name() -> str:
    from prefect.runtime import flow_run

    return f"train-{Path(str(flow_run.parameters.get('out_dir', 'model'))).name}"


@flow(name="tumor3d-train", flow_run_name=_train_run_name, persist_result=False)
def train_flow(
    manifest: str,
    out_dir: str,
    config: dict[str, Any] | None = None,
    store_dir: str | None = None,
    threshold: float = 0.5,
    t1c_threshold: float = 0.65,
    keep_fraction: float = 1.0,
    num_rounds: int = NUM_ROUNDS,
    command: str = "",
    cnn: bool = False,
    cnn_settings: dict[str, Any] | None = None,
    cnn_seeds: Sequence[int] = (0, 1),
    cnn_threads: int | None = None,
) -> TrainResult:
    """Train the learned segmentation's models on a manifest's labelled patients.

    Parameters
    ----------
    manifest : str
        Cohort manifest CSV; every row has a ``reference`` (or is ``tumor_free``).
    out_dir : str
        Where ``<family>.npz`` and ``training.json`` are written.
    config : dict, optional
        Pipeline configuration (preprocess, detect and the robust prior's
        segment settings); the same as the runs the model will serve.
    store_dir : str, optional
        Artifact store (default ``out_dir/.tumor3d-store``); share one with
        ``cohort`` to reuse its stages.
    threshold, t1c_threshold : float
        Probability threshold written into the FLAIR/T2 and the T1c model.
    keep_fraction : float
        Written into the models (:func:`tumor3d.learned.segment.keep_main_lesion`).
    num_rounds : int
        Boosting rounds.
    command : str
        The command line, recorded in the models and ``training.json``.
    cnn : bool
        Also train the U-Net on the FLAIR patients (PyTorch: the ``train`` extra).
    cnn_settings : dict, optional
        :class:`~tumor3d.learned.cnn_train.UNetSettings` fields other than the
        slice grid (``size``, ``context``, ``framing``: the unet-slices stage cuts
        every patient's slices on the shipped grid), e.g. ``{"epochs": 2}``; default
        the shipped network's.
    cnn_seeds : sequence of int
        One U-Net per seed (an ensemble; the shipped one: 0 and 1).
    cnn_threads : int, optional
        torch's threads (default torch's own choice).
    """
    logger = get_run_logger()
    cfg = parse_config(config or {}, source="config")
    rows = read_manifest(manifest)
    _check_rows(rows, str(manifest))
    unet_settings = None
    if cnn:  # before any patient's stages: a missing extra or a bad setting fails at once
        require_torch()
        extra = dict(cnn_settings or {})
        fixed = sorted(k for k in extra if k in _UNET_GRID)
        if fixed:
            raise InputError(f"cnn_settings: {', '.join(fixed)} is fixed by the unet-slices stage")
        try:
            unet_settings = UNetSettings(**extra)
        except TypeError as exc:
            raise InputError(f"cnn_settings: {exc}") from None
        if len(cnn_seeds) == 0 or len(set(cnn_seeds)) != len(cnn_seeds):
            raise InputError(f"cnn_seeds: give distinct seeds, got {list(cnn_seeds)}")
        if not any(r.modality in UNET_MODALITIES for r in rows):
            raise InputError("--cnn: the U-Net trains on FLAIR patients and the manifest has none")
    out = Path(out_dir)
    where = store_dir or default_store_location(out)
    store = open_store(where)
    work = Path(where) / "emulated"
    by_family: dict[str, list[tuple[TrainingRows, dict[str, Any]]]] = {}
    unet_cases: list[tuple[tuple[np.ndarray, np.ndarray], dict[str, Any]]] = []
    cached = 0
    for row in rows:
        try:
            rows_, case, slices = _patient_rows(row, cfg, store, work, cnn=cnn)
        except InputError as exc:
            raise InputError(f"patient {row.patient_id}: {exc.problem}", exc.path) from None
        cached += int(case["cached"])
        logger.info("%s: %d rows%s", row.patient_id, case["rows"],
                    " (cached)" if case["cached"] else "")  # fmt: skip
        by_family.setdefault(MODEL_FAMILIES[row.modality], []).append((rows_, case))
        if slices is not None:
            unet_cases.append((slices, case))
    result = TrainResult(out_dir=str(out), cached_patients=cached)
    files: dict[str, bytes] = {}
    for family, patients in sorted(by_family.items()):
        mods = sorted(m for m, f in MODEL_FAMILIES.items() if f == family)
        meta = {
            "name": f"tumor3d-{family}-{datetime.date.today().isoformat()}",
            "family": family,
            "modalities": mods,
            "threshold": float(t1c_threshold if family == "t1c" else threshold),
            "keep_fraction": float(keep_fraction),
            "prior": "robust",
            "training_cases": [c["patient_id"] for _, c in patients],
            "command": command,
        }
        n_lesion = sum(c["lesion_rows"] for _, c in patients)
        if n_lesion in (0, sum(c["rows"] for _, c in patients)):  # one class: say whose rows
            counts = ", ".join(f"{c['patient_id']} {c['lesion_rows']} of {c['rows']}"
                               for _, c in patients)  # fmt: skip
            raise InputError(
                f"the {family} model's training rows hold one class only (lesion rows per "
                f"patient: {counts}): does each reference overlap its image, and is some "
                "tissue outside the lesion?"
            )
        model = train_forest(
            TrainingRows.concatenate([r for r, _ in patients]), num_rounds=num_rounds, meta=meta
        )
        files[f"{family}.npz"] = model.to_bytes()
        result.models[family] = str(out / f"{family}.npz")
        for _, case in patients:
            case["family"] = family
        result.cases += [c for _, c in patients]
        logger.info("%s model: %d patients, %d trees, digest %s", family, len(patients),
                    model.roots.size, model.digest()[:12])  # fmt: skip
    if unet_settings is not None:
        x = np.concatenate([s[0] for s, _ in unet_cases])
        y = np.concatenate([s[1] for s, _ in unet_cases])
        for seed in cnn_seeds:
            name = f"unet_flair_seed{seed}"
            meta = {
                "name": f"tumor3d-unet-flair-seed{seed}-{datetime.date.today().isoformat()}",
                "modalities": list(UNET_MODALITIES),
                "input": "tumor3d.learned.cnn_data.case_input(image, size, context, "
                "frame_of(image, framing, pixel_mm))",
                "training_cases": [c["patient_id"] for _, c in unet_cases],
                "command": command,
            }
            data, fit = train_unet(
                x, y, unet_settings, seed=int(seed), threads=cnn_threads, meta=meta,
                log=lambda line, s=seed: logger.info("U-Net seed %d %s", s, line),
            )  # fmt: skip
            files[f"{name}.npz"] = data
            result.models[name] = str(out / f"{name}.npz")
            logger.info("U-Net seed %d: %d patients, %d slices, %.0f s", seed, len(unet_cases),
                        len(x), fit.seconds)  # fmt: skip
    card = {
        "command": command,
        "manifest": str(manifest),
        "threshold": threshold,
        "t1c_threshold": t1c_threshold,
        "keep_fraction": keep_fraction,
        "num_rounds": num_rounds,
        "cnn_settings": None if unet_settings is None else dataclasses.asdict(unet_settings),
        "models": {
            f.removesuffix(".npz"): {"file": f, "sha256": _sha256(b)} for f, b in files.items()
        },
        "cases": result.cases,
    }
    files["training.json"] = (json.dumps(card, indent=2) + "\n").encode()
    out.mkdir(parents=True, exist_ok=True)
    for name, data in files.items():  # each file whole or absent
        atomic_write_bytes(out / name, data)
    return result


def _sha256(data: bytes) -> str:
    import hashlib

    return hashlib.sha256(data).hexdigest()


def run_training(manifest: str | Path, out_dir: str | Path, **kwargs: Any) -> TrainResult:
    """Run :func:`train_flow` (keyword arguments as its parameters).

    Against the Prefect API :func:`tumor3d.flows.api_use.api_of_python_call` picks.
    """
    from tumor3d.flows.api_use import api_of_python_call

    with api_of_python_call():
        return train_flow(str(manifest), str(out_dir), **kwargs)
