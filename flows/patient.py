"""Single-patient flow: MR slices -> tumour masks, meshes, renders and volumes.

Wiring only: :func:`run_stages` runs the stages of :mod:`tumor3d.tasks.stages`
in order, each fed the inputs its declaration names; a runner
(:mod:`tumor3d.tasks.runner`) executes them; :func:`tumor3d.tasks.publish.publish_patient`
writes the files declared in :mod:`tumor3d.storage.derivatives` (staging folder,
fsync, rename swap); :func:`patient_flow` puts the report's summary on its
flow run (:mod:`tumor3d.flows.artifacts`).

:func:`patient_pipeline` is the whole single-patient pipeline inside a
running flow; :func:`patient_flow` is the Prefect flow around it and
:func:`tumor3d.flows.cohort.cohort_flow` runs it for many patients at once. Prefect's
results are kept in the artifact store by the runner itself, so a
deployment or parent flow calling :func:`patient_flow` directly gets the same
caching as :func:`run_patient`.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from prefect import flow, get_run_logger
from pydantic import BaseModel, ConfigDict

from tumor3d.config import PipelineConfig, as_config, parse_config
from tumor3d.constants import MAX_VOXELS_DEFAULT
from tumor3d.errors import InputError
from tumor3d.flows.artifacts import publish_patient_artifacts
from tumor3d.segmentation.review import NO_TUMOUR_NOTE
from tumor3d.storage import bids
from tumor3d.storage.brain_mask import GivenBrainMask, read_given_brain_mask
from tumor3d.storage.derivatives import VOLUME_LABELS, VOLUME_METHODS
from tumor3d.storage.given_models import models_for
from tumor3d.storage.given_segmentation import GivenSegmentation, read_given_segmentation
from tumor3d.storage.inputs import input_digest, input_location
from tumor3d.storage.objectstore import default_store_location, is_url, open_store
from tumor3d.storage.product_memo import products
from tumor3d.storage.provenance import cache_identity, changed_since
from tumor3d.storage.publish import check_destination, check_output_not_input
from tumor3d.storage.readers import (
    ReadOptions,
    derive_patient_id,
    resolve_modality,
    suggest_patient_id,
)
from tumor3d.storage.readers.handoff import kept_or_read
from tumor3d.storage.refs import ArtifactRef
from tumor3d.storage.store import ArtifactStore
from tumor3d.tasks import stages
from tumor3d.tasks.publish import (
    brain_mask_note,
    check_layout_destination,
    config_digest,
    metrics_row,
    publish_key,
    publish_patient,
    publish_results,
    run_notes,
    run_review,
)
from tumor3d.tasks.runner import DirectRunner, PrefectRunner, StageRun
from tumor3d.tasks.spec import InputSource

__all__ = [
    "DirectRunner",
    "NO_TUMOUR_NOTE",
    "PatientResult",
    "StageRun",
    "VOLUME_LABELS",
    "VOLUME_METHODS",
    "brain_mask_note",
    "config_digest",
    "patient_flow",
    "patient_pipeline",
    "prepare_brain_mask",
    "prepare_models",
    "prepare_segmentation",
    "prepare_source",
    "publish_key",
    "publish_patient",
    "run_patient",
    "run_stages",
    "run_notes",
    "run_stages_direct",
    "sweep_killed_writers",
]


class PatientResult(BaseModel):
    """What :func:`patient_flow` returns: where the outputs are and the headline numbers."""

    model_config = ConfigDict(frozen=True)

    patient_id: str
    output_dir: str
    metrics: dict[str, Any]
    stages: list[StageRun]
    flow_seconds: float
    #: Time spent publishing (reading the products back, encoding and writing the files).
    publish_seconds: float = 0.0
    notes: list[str] = []
    #: The content of ``report.html`` (:func:`tumor3d.storage.patient_outputs.patient_report_data`).
    report: dict[str, Any] = {}
    #: The output folder already held exactly this result: nothing was rewritten.
    up_to_date: bool = False
    #: Why stages ran for a patient published before in this folder
    #: (:func:`tumor3d.storage.provenance.recompute_reason`); None when all were cache
    #: hits or nothing was published.
    recomputed: str | None = None

    @property
    def cache_hits(self) -> list[bool]:
        """Per stage, whether it was a cache hit."""
        return [s.cached for s in self.stages]


def prepare_source(
    input_path: str | Path,
    options: ReadOptions | None = None,
    *,
    out_dir: str | Path | None = None,
    **option_keywords: Any,
) -> InputSource:
    """Validate the user's input and identify it by content.

    ``options`` (a :class:`~tumor3d.storage.readers.options.ReadOptions`), or
    its fields as keywords (``modality``, ``patient_id``, ``series_uid``,
    ``slice_thickness_mm``, ``slice_gap_mm``, ``skip_unreadable``,
    ``max_voxels``), say how to read it; without a modality, an image stack's
    sidecar names it, else it is ``"t2"``
    (:func:`tumor3d.storage.readers.resolve_modality`).

    With ``out_dir``, also refuse (before any work) an output folder
    ``<out_dir>/<patient_id>`` that is or contains the input, that holds
    files other than a tumor3d result, or (for an id derived from the file
    name) the results of another input (:func:`tumor3d.storage.publish.check_destination`).

    Raises
    ------
    InputError
        A missing input, unknown modality, unsafe patient id, or an output
        folder that would replace the input.
    """
    if options is None:
        options = ReadOptions(**option_keywords)  # checked here: one line naming the option
    elif option_keywords:
        raise TypeError("give prepare_source a ReadOptions or its fields, not both")
    path = Path(input_path).expanduser()
    if not path.exists():
        raise InputError("no such file or folder", path=str(path))
    patient_id = options.patient_id
    pid = patient_id if patient_id is not None else derive_patient_id(path)
    modality, origin = resolve_modality(path, options.modality)  # a stack's sidecar, else t2
    digest = input_digest(path)
    if out_dir is not None and not is_url(out_dir):  # an object store holds no local input
        check_destination(
            Path(out_dir) / pid, [path], derived_from=None if patient_id is not None else digest,
            location=input_location(path), suggestion=suggest_patient_id(path),
        )  # fmt: skip
    return InputSource(
        **{**options.model_dump(), "modality": modality, "patient_id": pid},
        path=str(path.resolve()),
        name=path.name,
        digest=digest,
        id_derived=patient_id is None,
        modality_default=origin == "default",
    )


def prepare_brain_mask(
    mask_path: str | Path,
    source: InputSource,
    *,
    out_dir: str | Path | None = None,
) -> GivenBrainMask:
    """Read a given brain mask and check it against the source's image, before any stage.

    The image is read as the ingest stage reads it (same options), the mask
    checked against its grid and content (:func:`tumor3d.storage.brain_mask.
    read_given_brain_mask`). With ``out_dir``, a mask inside the output
    folder ``<out_dir>/<patient_id>`` is refused as the input is.

    Raises
    ------
    InputError
        One line naming the mask file (or the image, if it is unreadable).
    """
    path = Path(mask_path).expanduser()
    if out_dir is not None and not is_url(out_dir):
        check_output_not_input(Path(out_dir) / source.patient_id, [path])
    image = kept_or_read(source.path, ReadOptions.of(source))
    return read_given_brain_mask(path, image, max_voxels=source.max_voxels)


def prepare_segmentation(
    mask_path: str | Path,
    source: InputSource,
    *,
    out_dir: str | Path | None = None,
) -> GivenSegmentation:
    """Read a given tumour segmentation and check it against the source's image.

    As :func:`prepare_brain_mask` (same grid rule, one line naming the file;
    with ``out_dir``, a mask inside ``<out_dir>/<patient_id>`` is refused):
    :func:`tumor3d.storage.given_segmentation.read_given_segmentation`.
    """
    path = Path(mask_path).expanduser()
    if out_dir is not None and not is_url(out_dir):
        check_output_not_input(Path(out_dir) / source.patient_id, [path])
    image = kept_or_read(source.path, ReadOptions.of(source))
    return read_given_segmentation(path, image, max_voxels=source.max_voxels)


def prepare_models(
    cfg: PipelineConfig, source: InputSource, segmentation: GivenSegmentation | None = None
) -> dict[str, bytes] | None:
    """The model files of ``segment.learned_models`` this patient's run uses, checked.

    :func:`tumor3d.storage.given_models.models_for` (None: unset, a given
    ``segmentation`` in place of the method, or a method that does not run the learned
    one on the scan's sequence; a folder without the sequence's forest is one line
    naming it). Read again for each patient (a few MB at most), so that the models a
    result was made with are those its cache key and provenance record.
    """
    return None if segmentation is not None else models_for(cfg, source.modality)


def run_stages(
    run: Any,
    source: InputSource,
    cfg: PipelineConfig,
    root: str,
    *,
    given: Mapping[str, ArtifactRef | None] | None = None,
) -> dict[str, Any]:
    """The pipeline: every stage of :data:`tumor3d.tasks.stages.STAGES` in order.

    Each is fed the references its declaration names
    (:func:`tumor3d.tasks.stages.stage_inputs`: the source, an earlier stage's
    product, a given mask) and its field of ``cfg``.

    ``run`` is a runner whose ``run(spec, **inputs)`` executes one stage and
    returns its :class:`~tumor3d.tasks.spec.StageOutput` (:class:`PrefectRunner`,
    :class:`DirectRunner`). ``given``: the given artifacts
    (:func:`tumor3d.tasks.stages.store_given`): a brain mask stored on the
    scan's grid replaces the skull removal of the preprocess stage (and
    enters its cache key); a tumour mask stored likewise replaces the
    segment-tumor stage's mask. Returns stage name -> output.
    """
    for spec in stages.STAGES.values():
        inputs = stages.stage_inputs(spec, run.outputs, source=source, cfg=cfg, given=given)
        run.run(spec, **inputs, store_root=root)
    return run.outputs


def patient_pipeline(
    source: InputSource,
    out_dir: str | Path,
    cfg: PipelineConfig,
    store: ArtifactStore,
    *,
    runs: list[StageRun] | None = None,
    brain_mask: GivenBrainMask | None = None,
    segmentation: GivenSegmentation | None = None,
    layout: str = "default",
) -> PatientResult:
    """Run every stage for one patient (inside a flow) and publish the results.

    ``runs``, if given, is filled with each stage's :class:`StageRun` as it
    completes (so a caller learns which stage failed). ``brain_mask``
    (:func:`prepare_brain_mask`) replaces the skull removal; it is stored
    as an artifact and recorded in the notes and ``provenance.json``;
    ``segmentation`` (:func:`prepare_segmentation`) likewise replaces the
    segment-tumor stage's mask. ``layout`` ``"bids"`` publishes BIDS derivatives
    (:mod:`tumor3d.storage.bids`) to ``out_dir/sub-<label>/``, a local ``out_dir`` only.
    A user's trained models (``segment.learned_models``, :func:`prepare_models`) are
    stored as an artifact the segment-tumor stage reads in place of the shipped ones.
    """
    t0 = time.perf_counter()
    pid = source.patient_id
    check_layout_destination(source, out_dir, layout, brain_mask, segmentation)  # before work
    models = prepare_models(cfg, source, segmentation)
    runner = PrefectRunner(store, pid, total=len(stages.STAGES), runs=runs)
    try:
        given = stages.store_given(
            store, brain_mask=brain_mask, segmentation=segmentation, models=models,
            models_folder=cfg.segment.learned_models,
        )  # fmt: skip
        outputs = run_stages(runner, source, cfg, str(store.root), given=given)
        flow_seconds = time.perf_counter() - t0
        notes, doubts = run_notes(
            outputs, brain_mask, segmentation, modality_default=source.modality_default
        )
        review = run_review(outputs, doubts)
        metrics = metrics_row(outputs, runner.runs, pid, flow_seconds, notes, review)
        t_publish = time.perf_counter()
        out_path, report, up_to_date = publish_results(
            store, out_dir, source, outputs, runner.runs, metrics, cfg, brain_mask, segmentation,
            layout=layout,
        )  # fmt: skip
    finally:  # published or failed: its volumes leave this process's memo (a warm runner stays)
        forget_products(runner.runs)
    return PatientResult(
        patient_id=pid, output_dir=str(out_path), metrics=metrics, stages=runner.runs,
        flow_seconds=flow_seconds, publish_seconds=time.perf_counter() - t_publish, notes=notes,
        report=report, up_to_date=up_to_date,
    )  # fmt: skip


def forget_products(runs: list[StageRun]) -> None:
    """Drop a patient's stage volumes from the memo of decoded volumes (product_memo)."""
    products().discard(d for run in runs for d in run.artifacts.values())


def _flow_run_name() -> str:
    from prefect.runtime import flow_run

    params = flow_run.parameters
    pid = params.get("patient_id")
    if not pid:  # the id the run will publish under (as the README says), not the file name
        path = Path(str(params.get("input_path", "input")))
        try:
            pid = derive_patient_id(path)
        except InputError:
            pid = path.name
    return f"patient-{pid}"


@flow(name="tumor3d-patient", flow_run_name=_flow_run_name, persist_result=False, log_prints=False)
def patient_flow(
    input_path: str,
    out_dir: str,
    patient_id: str | None = None,
    config: dict[str, Any] | None = None,
    modality: str | None = None,
    slice_thickness_mm: float | None = None,
    slice_gap_mm: float | None = None,
    series_uid: str | None = None,
    store_dir: str | None = None,
    skip_unreadable: bool = False,
    max_voxels: int = MAX_VOXELS_DEFAULT,
    brain_mask: str | None = None,
    segmentation: str | None = None,
    layout: str = "default",
) -> PatientResult:
    """Reconstruct one patient's tumour and publish masks, meshes, renders and metrics.

    The summary also goes onto the flow run as a markdown and a table
    artifact (:mod:`tumor3d.flows.artifacts`).

    Parameters
    ----------
    input_path : str
        NIfTI file, DICOM series folder, or folder of 2-D slices with a YAML sidecar.
    out_dir : str
        Outputs go to ``<out_dir>/<patient_id>/`` (never a folder holding the input).
    patient_id : str, optional
        Folder-safe id; derived from the input's name if omitted.
    config : dict, optional
        Pipeline configuration (validated into :class:`PipelineConfig`).
    modality : {"t2", "flair", "t1c"}, optional
        None: what an image stack's sidecar names, else ``"t2"``, which the run's
        notes then say (:func:`prepare_source`).
    slice_thickness_mm, slice_gap_mm : float, optional
        Override what the input says about its slices.
    series_uid : str, optional
        Which DICOM series to read when a folder holds several.
    store_dir : str, optional
        Artifact store (and Prefect's results); default ``<out_dir>/.tumor3d-store``.
    skip_unreadable : bool
        Skip DICOM files that cannot be read instead of stopping; they are
        named in the summary's notes, ``metrics.parquet`` and provenance.
    max_voxels : int
        Refuse an input whose header declares more voxels (before reading it).
    brain_mask : str, optional
        A brain mask on the input's voxel grid (brain = values > 0.5) used
        instead of skull removal (:func:`prepare_brain_mask`).
    segmentation : str, optional
        A tumour mask on the input's voxel grid (tumour = values > 0.5) used
        instead of the segment-tumor stage's (:func:`prepare_segmentation`).
    layout : {"default", "bids"}
        ``"bids"``: BIDS derivatives under ``<out_dir>/sub-<label>/`` with
        ``<out_dir>/dataset_description.json`` (:mod:`tumor3d.storage.bids`).
    """
    cfg = parse_config(config or {}, source="config")
    source = prepare_source(
        input_path, patient_id=patient_id, modality=modality, series_uid=series_uid,
        slice_thickness_mm=slice_thickness_mm, slice_gap_mm=slice_gap_mm,
        skip_unreadable=skip_unreadable, max_voxels=max_voxels, out_dir=out_dir,
    )  # fmt: skip
    given = None if brain_mask is None else prepare_brain_mask(brain_mask, source, out_dir=out_dir)
    seg = None
    if segmentation is not None:
        seg = prepare_segmentation(segmentation, source, out_dir=out_dir)
    prepare_models(cfg, source, seg)  # a folder without the scan's model: before any writing
    with _writing_patient(out_dir, bids.folder_name(source.patient_id, layout)):
        return _run_and_publish(
            source, out_dir, cfg, given, seg, store_dir=store_dir, layout=layout
        )


def _run_and_publish(
    source: InputSource,
    out_dir: str,
    cfg: PipelineConfig,
    given: GivenBrainMask | None,
    seg: GivenSegmentation | None,
    *,
    store_dir: str | None,
    layout: str,
) -> PatientResult:
    """:func:`patient_flow`'s stages and publishing, once its inputs are checked."""
    store = open_store(store_dir or default_store_location(out_dir))  # s3:// -> ObjectStore
    logger = get_run_logger()
    digest = config_digest(cfg)[:12]
    logger.info("patient %s: %s (config %s)", source.patient_id, source.name, digest)
    # what decided the published result's cache keys, to say why stages run again
    before = None if is_url(out_dir) else cache_identity(
        Path(out_dir) / bids.folder_name(source.patient_id, layout)
    )  # fmt: skip
    result = patient_pipeline(
        source, out_dir, cfg, store, brain_mask=given, segmentation=seg, layout=layout
    )
    reason = None if before is None else changed_since(
        before, result.output_dir, all(result.cache_hits)
    )  # fmt: skip
    if reason is not None:  # a warning: the flow run's log on the server (not the console)
        result = result.model_copy(update={"recomputed": reason})
        logger.warning("patient %s changed since its earlier result: %s", source.patient_id,
                       reason)  # fmt: skip
    publish_patient_artifacts(result.report)
    logger.info("patient %s: published %s", source.patient_id, result.output_dir)
    sweep_killed_writers(store, logger)  # an earlier run's, killed mid-write
    return result


def sweep_killed_writers(store: ArtifactStore, logger: Any) -> None:
    """Remove the store's temporary files of writers killed mid-write, and say so.

    Housekeeping at the end of a patient or cohort flow
    (:meth:`~tumor3d.storage.store.ArtifactStore.clean_stale_tmp`): it never fails
    the run; a sweep that cannot be made is one warning line.
    """
    try:
        swept = store.clean_stale_tmp()
    except Exception as exc:  # noqa: BLE001
        logger.warning("could not sweep the store's temporary files: %s", exc)
        return
    if swept:
        logger.info("removed %d temporary object file(s) of killed writers", len(swept))


def run_stages_direct(
    input_path: str | Path,
    store_dir: str | Path,
    *,
    config: dict[str, Any] | PipelineConfig | None = None,
    patient_id: str | None = None,
    modality: str = "t2",
    brain_mask: str | Path | None = None,
    segmentation: str | Path | None = None,
) -> DirectRunner:
    """Run every stage in this process without Prefect; artifacts go to ``store_dir``."""
    cfg = config if isinstance(config, PipelineConfig) else parse_config(config or {})
    source = prepare_source(input_path, patient_id=patient_id, modality=modality)
    store = ArtifactStore(store_dir)
    given = None if brain_mask is None else prepare_brain_mask(brain_mask, source)
    seg = None if segmentation is None else prepare_segmentation(segmentation, source)
    runner = DirectRunner(source.patient_id, len(stages.STAGES))
    models = prepare_models(cfg, source, seg)
    stored = stages.store_given(
        store, brain_mask=given, segmentation=seg, models=models,
        models_folder=cfg.segment.learned_models,
    )  # fmt: skip
    run_stages(runner, source, cfg, str(store.root), given=stored)
    return runner


def run_patient(input_path: str | Path, out_dir: str | Path, **kwargs: Any) -> PatientResult:
    """Run :func:`patient_flow`, tagged with the configuration's digest.

    Keyword arguments are those of :func:`patient_flow`; ``config`` may also be a
    :class:`PipelineConfig` or YAML text (:func:`tumor3d.config.as_config`). Before any
    flow run or server: an unknown keyword is Python's TypeError, an input path that
    does not exist an InputError naming it.
    """
    import inspect

    from prefect import tags

    from tumor3d.flows.api_use import api_of_python_call

    inspect.signature(patient_flow.fn).bind(str(input_path), str(out_dir), **kwargs)
    cfg = as_config(kwargs.get("config"))
    kwargs["config"] = cfg.model_dump(mode="json")
    if not Path(input_path).exists():
        raise InputError("no such file or folder", path=str(input_path))
    with api_of_python_call(), tags(f"config:{config_digest(cfg)[:12]}"):
        return patient_flow(str(input_path), str(out_dir), **kwargs)


@contextlib.contextmanager
def _writing_patient(out_dir: str, folder: str) -> Iterator[None]:
    """Hold a local output folder's lock shared and the patient's folder's exclusively.

    :mod:`tumor3d.storage.folder_lock`: runs of other patients into the folder go on
    together, a second run of this patient (or a cohort command on the folder) stops at
    once with one line. Taken once the input and the destination are checked (a refused
    run writes nothing); an object store's output is not locked.
    """
    from tumor3d.storage.folder_lock import patient_lock_name, writing_folder

    if is_url(out_dir):
        yield
        return
    out = Path(out_dir)
    with writing_folder(out, shared=True), writing_folder(out, name=patient_lock_name(folder)):
        yield
