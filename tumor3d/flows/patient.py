"""Single-patient flow: MR slices -> tumour masks, meshes, renders and volumes.

Wiring only: :func:`run_stages` orders the stages of :mod:`tumor3d.tasks.stages`
and feeds each its inputs' references; a runner (:mod:`tumor3d.tasks.runner`)
executes them; :func:`publish_patient` hands the results to
:mod:`tumor3d.storage.publish` (staging folder, fsync, rename swap),
:mod:`tumor3d.storage.slice_table`, :mod:`tumor3d.storage.provenance` and
:mod:`tumor3d.storage.patient_outputs` (overlays, viewer files, ``report.html``);
:func:`patient_flow` puts the report's summary on its flow run
(:mod:`tumor3d.flows.artifacts`).

:func:`patient_pipeline` is the whole single-patient pipeline inside a
running flow; :func:`patient_flow` is the Prefect flow around it and
:func:`tumor3d.flows.cohort.cohort_flow` runs it for many patients at once. Prefect's
results are kept in the artifact store by the runner itself, so a
deployment or parent flow calling :func:`patient_flow` directly gets the same
caching as :func:`run_patient`.
"""

from __future__ import annotations

import hashlib
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import pandas as pd
from prefect import flow, get_run_logger
from pydantic import BaseModel, ConfigDict

from tumor3d.config import PipelineConfig, parse_config
from tumor3d.constants import MAX_VOXELS_DEFAULT
from tumor3d.errors import InputError
from tumor3d.flows.artifacts import publish_patient_artifacts
from tumor3d.metrics import EQ7_SLICE_RULES
from tumor3d.segmentation.review import NO_TUMOUR_NOTE, Review, review_status
from tumor3d.segmentation.review import run_notes as review_notes
from tumor3d.storage import bids, nifti
from tumor3d.storage.brain_mask import GivenBrainMask, read_given_brain_mask
from tumor3d.storage.formats import encode_parquet
from tumor3d.storage.given_segmentation import GivenSegmentation, read_given_segmentation
from tumor3d.storage.inputs import input_digest, input_location
from tumor3d.storage.objectstore import default_store_location, is_url, open_store
from tumor3d.storage.patient_outputs import (
    join_notes,
    patient_report_data,
    split_notes,
    write_overlays,
    write_report,
    write_surface_files,
)
from tumor3d.storage.provenance import build_provenance, versions
from tumor3d.storage.publish import (
    PUBLISH_MANIFEST,
    check_destination,
    check_output_not_input,
    check_same_input,
    clean_stale_staging,
    published_is_current,
    staged_folder,
    write_publish_manifest,
)
from tumor3d.storage.readers import ReadOptions, derive_patient_id, suggest_patient_id
from tumor3d.storage.readers.handoff import kept_or_read
from tumor3d.storage.remote_publish import publish_folder
from tumor3d.storage.slice_table import slice_table
from tumor3d.storage.store import (
    ArtifactRef,
    ArtifactStore,
    canonical_dumps,
    source_grid_from_metadata,
)
from tumor3d.storage.viewer import ASSETS_DIR, write_viewer_assets
from tumor3d.tasks import stages
from tumor3d.tasks.preprocess import preprocess_notes
from tumor3d.tasks.runner import DirectRunner, PrefectRunner, StageRun
from tumor3d.tasks.spec import InputSource, StageOutput

__all__ = [
    "DirectRunner",
    "NO_TUMOUR_NOTE",
    "PatientResult",
    "StageRun",
    "VOLUME_LABELS",
    "VOLUME_METHODS",
    "brain_mask_note",
    "config_digest",
    "default_store_dir",
    "patient_flow",
    "patient_pipeline",
    "prepare_brain_mask",
    "prepare_segmentation",
    "prepare_source",
    "publish_key",
    "publish_patient",
    "run_patient",
    "run_stages",
    "run_notes",
    "run_stages_direct",
]

#: Volume columns of metrics.parquet and the method each names.
VOLUME_METHODS: dict[str, str] = {
    "volume_eq7_mm3": "Eq. 7: (thickness + gap) x sum of tumour areas over every acquired "
    "slice with segmented tumour (the abnormal slices and the tumour's end slices)",
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


class PatientResult(BaseModel):
    """What :func:`patient_flow` returns: where the outputs are and the headline numbers."""

    model_config = ConfigDict(frozen=True)

    patient_id: str
    output_dir: str
    metrics: dict[str, Any]
    stages: list[StageRun]
    flow_seconds: float
    notes: list[str] = []
    #: The content of ``report.html`` (:func:`tumor3d.storage.patient_outputs.patient_report_data`).
    report: dict[str, Any] = {}
    #: The output folder already held exactly this result: nothing was rewritten.
    up_to_date: bool = False

    @property
    def cache_hits(self) -> list[bool]:
        """Per stage, whether it was a cache hit."""
        return [s.cached for s in self.stages]


def default_store_dir(out_dir: str | Path) -> Path | str:
    """The artifact store used when none is given: ``<out_dir>/.tumor3d-store``.

    :func:`tumor3d.storage.objectstore.default_store_location`, the one definition.
    """
    return default_store_location(out_dir)


def config_digest(cfg: PipelineConfig) -> str:
    """SHA-256 of the canonical JSON of a whole configuration."""
    return hashlib.sha256(canonical_dumps(cfg.model_dump(mode="json")).encode()).hexdigest()


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
    ``max_voxels``), say how to read it; the modality defaults to ``"t2"``.

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
    digest = input_digest(path)
    if out_dir is not None and not is_url(out_dir):  # an object store holds no local input
        check_destination(
            Path(out_dir) / pid, [path], derived_from=None if patient_id is not None else digest,
            location=input_location(path), suggestion=suggest_patient_id(path),
        )  # fmt: skip
    return InputSource(
        **{**options.model_dump(), "modality": options.modality or "t2", "patient_id": pid},
        path=str(path.resolve()),
        name=path.name,
        digest=digest,
        id_derived=patient_id is None,
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


def _store_segmentation(store: ArtifactStore, seg: GivenSegmentation | None) -> ArtifactRef | None:
    """Put a given segmentation in the store; its file name rides along (``measured``)."""
    if seg is None:
        return None
    return store.put_volume(seg.mask, seg.affine, kind="mask", extra={"given_file": seg.name})


def _given_inputs(
    brain_mask: GivenBrainMask | None, segmentation: GivenSegmentation | None
) -> list[str]:
    """The given mask files (never inside the output folder, never modified)."""
    return [m.path for m in (brain_mask, segmentation) if m is not None]


def brain_mask_note(mask: GivenBrainMask) -> str:
    """The note a run with a given brain mask carries (summary, metrics, provenance)."""
    return f"brain mask given ({mask.name}, SHA-256 {mask.sha256[:12]}...): no skull removal"


def run_stages(
    run: Any,
    source: InputSource,
    cfg: PipelineConfig,
    root: str,
    *,
    brain_mask: ArtifactRef | None = None,
    segmentation: ArtifactRef | None = None,
) -> dict[str, Any]:
    """The pipeline: every stage of :data:`tumor3d.tasks.stages.STAGES` in order.

    Each is fed the references its declaration names
    (:func:`tumor3d.tasks.stages.stage_inputs`: the source, an earlier stage's
    product, a given mask) and its field of ``cfg``.

    ``run`` is a runner whose ``run(spec, **inputs)`` executes one stage and
    returns its :class:`~tumor3d.tasks.spec.StageOutput` (:class:`PrefectRunner`,
    :class:`DirectRunner`). ``brain_mask``, a given mask stored on the
    scan's grid, replaces the skull removal of the preprocess stage (and
    enters its cache key); ``segmentation``, a given tumour mask stored
    likewise, replaces the segment-tumor stage's mask. Returns stage name -> output.
    """
    given = {"brain_mask": brain_mask, "segmentation": segmentation}
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
    """
    t0 = time.perf_counter()
    pid = source.patient_id
    check_layout_destination(source, out_dir, layout, brain_mask, segmentation)
    runner = PrefectRunner(store, pid, total=len(stages.STAGES), runs=runs)
    mask_ref = _store_brain_mask(store, brain_mask)
    seg_ref = _store_segmentation(store, segmentation)
    outputs = run_stages(
        runner, source, cfg, str(store.root), brain_mask=mask_ref, segmentation=seg_ref
    )
    flow_seconds = time.perf_counter() - t0
    notes, doubts = run_notes(outputs, brain_mask, segmentation)
    review = review_status(doubts, segmentation=outputs["segment-tumor"].values)
    metrics = _metrics_row(outputs, runner.runs, pid, flow_seconds, notes, review)
    if is_url(out_dir):  # staged locally, then uploaded (tumor3d.storage.remote_publish)
        with tempfile.TemporaryDirectory(prefix="tumor3d-publish-") as tmp:
            staged, report, _ = publish_patient(
                store, Path(tmp), source, outputs, runner.runs, metrics, cfg, brain_mask,
                segmentation,
            )  # fmt: skip
            reused = all(r.cached and not r.repaired for r in runner.runs)
            # publish_folder skips an unchanged upload, and with reuse a folder of the same key
            out_path = publish_folder(staged, f"{str(out_dir).rstrip('/')}/{pid}", reuse=reused)
            # the viewer's shared script (unchanged bytes are read back, not uploaded)
            publish_folder(Path(tmp) / ASSETS_DIR, f"{str(out_dir).rstrip('/')}/{ASSETS_DIR}")
        up_to_date = False
    else:
        out_path, report, up_to_date = publish_patient(
            store, Path(out_dir), source, outputs, runner.runs, metrics, cfg, brain_mask,
            segmentation, layout=layout,
        )  # fmt: skip
    return PatientResult(
        patient_id=pid, output_dir=str(out_path), metrics=metrics, stages=runner.runs,
        flow_seconds=flow_seconds, notes=notes, report=report, up_to_date=up_to_date,
    )  # fmt: skip


def check_layout_destination(
    source: InputSource,
    out_dir: str | Path,
    layout: str,
    brain_mask: GivenBrainMask | None = None,
    segmentation: GivenSegmentation | None = None,
) -> None:
    """Before any work: ``layout`` known; for BIDS a valid label, a local ``out_dir`` of ours.

    :func:`tumor3d.storage.bids.participant_label` (one line naming the id) and
    :func:`tumor3d.storage.bids.check_dataset_root` (``OUT/dataset_description.json``
    absent or a tumor3d derivative's, never an input).
    """
    if bids.check_layout(layout) != "bids":
        return
    bids.participant_label(source.patient_id)
    if is_url(out_dir):
        raise InputError(
            "--layout bids writes a local folder (dataset_description.json beside the "
            "subjects): give a local --out",
            path=str(out_dir),
        )
    bids.check_dataset_root(out_dir, [source.path] + _given_inputs(brain_mask, segmentation))


def run_notes(
    outputs: dict[str, StageOutput],
    brain_mask: GivenBrainMask | None = None,
    segmentation: GivenSegmentation | None = None,
) -> tuple[list[str], list[str]]:
    """The run's notes (summary, metrics, provenance) and those that doubt the result.

    :func:`tumor3d.segmentation.review.run_notes` on the stages' values: the doubts make
    the status ``check`` (:func:`tumor3d.segmentation.review.review_status`). A given
    segmentation adds an informational note (``segmentation: given (FILE, ...)``),
    as do nibabel's repairs of the input's NIfTI header (the ingest-scan stage's
    ``header_notes``).
    """
    notes, doubts = review_notes(
        tumour_found=outputs["extract-surface"].values["faces"] > 0,
        caveats=outputs["segment-tumor"].values.get("caveats") or [],
        skipped_files=outputs["ingest-scan"].values.get("skipped_files") or [],
        brain_mask_note=None if brain_mask is None else brain_mask_note(brain_mask),
        brain_notes=preprocess_notes(outputs["preprocess"].values),
    )
    # nibabel's repairs of a NIfTI header (tumor3d.tasks.ingest): informational, never printed
    notes.extend(outputs["ingest-scan"].values.get("header_notes") or [])
    if segmentation is not None:
        notes.append(segmentation.note())
    return notes, doubts


def _store_brain_mask(store: ArtifactStore, mask: GivenBrainMask | None) -> ArtifactRef | None:
    """Put a given brain mask in the store (content-addressed: the same mask, the same ref)."""
    if mask is None:
        return None
    return store.put_volume(mask.mask, mask.affine, kind="mask")


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
    modality: str = "t2",
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
    modality : {"t2", "flair", "t1c"}
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
    store = open_store(store_dir or default_store_dir(out_dir))  # s3:// -> ObjectStore
    logger = get_run_logger()
    digest = config_digest(cfg)[:12]
    logger.info("patient %s: %s (config %s)", source.patient_id, source.name, digest)
    result = patient_pipeline(
        source, out_dir, cfg, store, brain_mask=given, segmentation=seg, layout=layout
    )
    publish_patient_artifacts(result.report)
    logger.info("patient %s: published %s", source.patient_id, result.output_dir)
    return result


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
    run_stages(
        runner, source, cfg, str(store.root), brain_mask=_store_brain_mask(store, given),
        segmentation=_store_segmentation(store, seg),
    )  # fmt: skip
    return runner


def run_patient(input_path: str | Path, out_dir: str | Path, **kwargs: Any) -> PatientResult:
    """Run :func:`patient_flow`, tagged with the configuration's digest.

    Keyword arguments are those of :func:`patient_flow`.
    """
    from prefect import tags

    cfg = parse_config(kwargs.get("config") or {}, source="config")
    with tags(f"config:{config_digest(cfg)[:12]}"):
        return patient_flow(str(input_path), str(out_dir), **kwargs)


def _metrics_row(
    outputs: dict[str, StageOutput],
    runs: list[StageRun],
    pid: str,
    flow_seconds: float,
    notes: list[str],
    review: Review,
) -> dict[str, Any]:
    row: dict[str, Any] = {"patient_id": pid}
    # ok or check (a failed run publishes no metrics); tumor3d.segmentation.review decides
    row["status"] = review.status
    row["needs_review"] = review.needs_review
    row["review_reasons"] = join_notes(review.reasons)
    if review.quality_score is not None:  # a segmentation method that scores itself
        row["segmentation_quality_score"] = float(review.quality_score)
    row.update(stages.metric_columns(outputs))  # each stage's declared columns
    row["tumour_found"] = row["faces_mc"] > 0
    row["notes"] = join_notes(notes)
    for r in runs:
        key = r.stage.replace("-", "_")
        row[f"time_{key}_s"] = float(r.compute_seconds)
        row[f"cached_{key}"] = bool(r.cached)
    row["time_flow_s"] = float(flow_seconds)
    return row


#: The modules whose code writes a published folder (with :data:`__name__`, this one).
PUBLISHER_MODULES = (
    "tumor3d.storage.bids", "tumor3d.storage.formats", "tumor3d.storage.nifti",
    "tumor3d.storage.patient_outputs", "tumor3d.storage.provenance",
    "tumor3d.storage.publish", "tumor3d.storage.slice_table", "tumor3d.segmentation.review",
)  # fmt: skip


def _publisher_code_digest() -> str:
    """The code digest of this module and :data:`PUBLISHER_MODULES`' closure.

    :func:`tumor3d.tasks.caching.code_digest` (syntax trees: a comment or docstring
    does not republish), with the store codecs included: they encode
    published files too.
    """
    from tumor3d.tasks.caching import code_digest

    return code_digest((__name__, *PUBLISHER_MODULES), include_codecs=True)


def publish_key(
    source: InputSource,
    outputs: dict[str, StageOutput],
    cfg: PipelineConfig,
    brain_mask: GivenBrainMask | None = None,
    segmentation: GivenSegmentation | None = None,
    layout: str = "default",
) -> str:
    """SHA-256 of everything a published folder is made from.

    The input's identity (not its location), every stage output's content
    digest (artifact digests and values), the configuration, each stage's
    code digest, the publisher's code (:func:`_publisher_code_digest`) and
    the recorded package versions, and a given brain mask's name and
    SHA-256 (recorded in provenance). Equal keys mean the folder's content
    would be the same, except the run's own times and cache flags.
    """
    doc: dict[str, Any] = {
        "source": source.model_dump(mode="json", exclude={"path"}),
        "outputs": {name: out.content_digest() for name, out in sorted(outputs.items())},
        "config_sha256": config_digest(cfg),
        "stage_code": {name: spec.code_digest for name, spec in stages.STAGES.items()},
        "publisher": _publisher_code_digest(),
        "versions": versions(),
    }
    if brain_mask is not None:
        doc["brain_mask"] = brain_mask.provenance()
    if segmentation is not None:
        doc["segmentation"] = segmentation.provenance()
    if layout != "default":  # the default layout's keys stay those published before
        doc["layout"] = layout
    return hashlib.sha256(canonical_dumps(doc).encode()).hexdigest()


def _current_report(
    folder: Path,
    store: ArtifactStore,
    outputs: dict[str, StageOutput],
    runs: list[StageRun],
    metrics: dict[str, Any],
    label: str | None = None,
) -> dict[str, Any]:
    """The report content of an up-to-date published folder, for this run's artifacts.

    ``label``: a BIDS folder (``sub-<label>``), whose files are found under their BIDS paths.
    """
    det = store.get_table(outputs["detect-abnormal"].artifacts["detection"])
    abnormal = det.loc[det["abnormal"].astype(bool), "slice_index"].astype(int).tolist()
    files = sorted(f.name for f in folder.iterdir() if f.is_file() and f.name != PUBLISH_MANIFEST)
    names = None
    if label is not None:
        names = {k: v for k, v in bids.bids_names(label).items() if (folder / v).is_file()}
        files += list(names)
    return patient_report_data(
        metrics, stage_runs=[r.model_dump() for r in runs], abnormal_slices=abnormal,
        files=files, provenance=json.loads((folder / "provenance.json").read_text()),
        names=names,
    )  # fmt: skip


def publish_patient(
    store: ArtifactStore,
    out_dir: Path,
    source: InputSource,
    outputs: dict[str, StageOutput],
    runs: list[StageRun],
    metrics: dict[str, Any],
    cfg: PipelineConfig,
    brain_mask: GivenBrainMask | None = None,
    segmentation: GivenSegmentation | None = None,
    *,
    layout: str = "default",
) -> tuple[Path, dict[str, Any], bool]:
    """Write the patient's outputs to a staging folder, then swap it into ``out_dir/<id>``.

    Skipped when every stage was a cache hit (none repaired) and
    ``out_dir/<id>`` already holds exactly this result
    (:func:`tumor3d.storage.publish.published_is_current` with :func:`publish_key`:
    same key, every file present with its published digest): the folder,
    its ``provenance.json`` and ``metrics.parquet`` then still describe the
    run that wrote them.

    Returns the folder, the report's content (:func:`tumor3d.storage.patient_outputs.
    patient_report_data`, also the Prefect artifacts' source) and whether
    the folder was already up to date (nothing written).

    ``layout="bids"``: the same files, renamed and with sidecars, in
    ``out_dir/sub-<label>/`` (:func:`tumor3d.storage.bids.relayout`), and the dataset's
    ``dataset_description.json`` and ``.bidsignore`` in ``out_dir``.
    """
    pid = source.patient_id
    folder = bids.folder_name(pid, layout)
    label = bids.participant_label(pid) if layout == "bids" else None
    inputs = [source.path] + _given_inputs(brain_mask, segmentation)
    check_output_not_input(out_dir / folder, inputs)
    key = publish_key(source, outputs, cfg, brain_mask, segmentation, layout)
    write_viewer_assets(out_dir)  # viewer.html's script, once per output folder
    raw = bids.raw_source(source.path) if label is not None else None
    if label is not None:
        bids.check_dataset_root(out_dir, inputs)
        bids.write_dataset_files(out_dir, None if raw is None else raw[0])
    reused = all(r.cached and not r.repaired for r in runs)
    if reused and published_is_current(out_dir / folder, key):
        clean_stale_staging(out_dir, folder)
        try:
            report = _current_report(out_dir / folder, store, outputs, runs, metrics, label)
        except (OSError, ValueError):  # changed since the check: publish again
            pass
        else:
            return out_dir / folder, report, True
    scan_ref = outputs["ingest-scan"].artifacts["scan"]
    grid = source_grid_from_metadata(scan_ref.metadata)
    tumour_found = bool(metrics["tumour_found"])
    art = {name: out.artifacts for name, out in outputs.items()}
    same_input = None
    if source.id_derived:  # checked again right before the swap: a concurrent run's folder
        location = input_location(source.path)

        def same_input(final: Path) -> None:
            check_same_input(final, source.digest, location=location)

    with staged_folder(out_dir, folder, check=same_input) as staging:
        files: list[str] = []

        def put(name: str, data: bytes) -> None:
            (staging / name).write_bytes(data)
            files.append(name)

        slices_mask, _ = store.get_volume(art["segment-tumor"]["tumor_mask_slices"])
        put("tumor_mask_slices.nii.gz", nifti.mask_to_source_nifti_bytes(slices_mask, grid))
        if "tumor_probability" in art["segment-tumor"]:  # the learned method's confidence
            prob, prob_affine = store.get_volume(art["segment-tumor"]["tumor_probability"])
            put(
                "tumor_probability.nii.gz",
                nifti.volume_to_source_nifti_bytes(prob, prob_affine, grid, dtype="float32"),
            )
        brain, _ = store.get_volume(art["preprocess"]["brain_mask"])
        put("brain_mask.nii.gz", nifti.mask_to_source_nifti_bytes(brain, grid))
        fine, fine_affine = store.get_volume(art["interpolate-slices"]["tumor_mask"])
        put(
            "tumor_mask.nii.gz",
            nifti.volume_to_source_nifti_bytes(fine, fine_affine, grid, dtype="uint8"),
        )
        if tumour_found:  # no 0-vertex PLY files when there is no tumour
            put("tumor.ply", store.get_bytes(art["extract-surface"]["mesh"]))
            put("tumor_simplified.ply", store.get_bytes(art["simplify-mesh"]["mesh"]))
        scan_image, scan_affine = store.get_volume(scan_ref)  # the viewer's MR slices
        files += write_surface_files(
            staging,
            tumour=store.get_mesh(art["extract-surface"]["mesh"]),
            simplified=store.get_mesh(art["simplify-mesh"]["mesh"]),
            brain=store.get_mesh(art["extract-brain-surface"]["brain_mesh"]),
            brain_viewer=store.get_mesh(art["extract-brain-surface"]["brain_mesh_viewer"]),
            image_zyx=scan_image, affine=scan_affine, tumour_mask=slices_mask, brain_mask=brain,
            title=f"tumor3d: {pid}", tumor_color_rgb=cfg.render.color_rgb,
            brain_color_rgb=cfg.render.brain_color_rgb, brain_opacity=cfg.render.brain_opacity,
        )  # fmt: skip
        det = store.get_table(art["detect-abnormal"]["detection"])
        abnormal = det.loc[det["abnormal"].astype(bool), "slice_index"].astype(int).tolist()
        image, affine = store.get_volume(art["preprocess"]["enhanced"])
        files += write_overlays(staging, image, affine, brain, slices_mask, abnormal)
        for name, ref in art["render-views"].items():
            put(f"{name}{Path(ref.relpath).suffix}", store.get_bytes(ref))
        table = slice_table(
            det,
            store.get_table(art["segment-tumor"]["segmentation"]),
            pixel_area_mm2=outputs["measure-volume"].values["pixel_area_mm2"],
        )
        put("slices.parquet", encode_parquet(table))
        put("metrics.parquet", encode_parquet(pd.DataFrame([metrics])))
        rule = str(metrics.get("eq7_slice_rule", "segmented"))
        input_info = {
            "name": source.name,
            "digest_sha256": source.digest,
            "location_sha256": input_location(source.path),
        }
        input_info.update(modality=source.modality, patient_id=pid)
        code = {name: spec.code_digest for name, spec in stages.STAGES.items()}
        provenance = build_provenance(
            input_info=input_info,
            config=cfg.model_dump(mode="json"),
            config_digest=config_digest(cfg),
            stages=[{**r.model_dump(), "code_sha256": code[r.stage]} for r in runs],
            volume_methods=VOLUME_METHODS,
            eq7_slice_rule={"name": rule, "definition": EQ7_SLICE_RULES[rule]},
            notes=split_notes(metrics.get("notes")),
        )
        render = outputs["render-views"].values
        provenance["render"] = {k: render.get(k) for k in ("renderer", "fallback_reason")}
        provenance["brain_mask"] = (
            {
                "given": False,
                "rule": "found from the image (preprocess brain_extraction)",
                # the extraction that ran ("auto" resolved); absent in results cached
                # before the stage recorded it
                "extraction": outputs["preprocess"].values.get("brain_extraction"),
            }
            if brain_mask is None
            else brain_mask.provenance()
        )
        provenance["segmentation"] = (
            {
                "given": False,
                "method": outputs["segment-tumor"].values.get("segment_method"),
                # the learned method's model: its name and digest (absent for the others)
                **{
                    k: outputs["segment-tumor"].values[k]
                    for k in ("model", "model_sha256")
                    if k in outputs["segment-tumor"].values
                },
            }
            if segmentation is None
            else segmentation.provenance()
        )
        (staging / "provenance.json").write_text(json.dumps(provenance, indent=2) + "\n")
        files.append("provenance.json")
        names = None
        if label is not None:  # BIDS names, sidecars and GIFTI surfaces (tumor3d.storage.bids)
            names = bids.relayout(
                staging, label, files, metrics=metrics, volume_methods=VOLUME_METHODS,
                raw_uri=None if raw is None else f"bids:raw:{raw[1]}",
            )  # fmt: skip
        report = patient_report_data(
            metrics, stage_runs=[r.model_dump() for r in runs], abnormal_slices=abnormal,
            files=files, provenance=provenance, names=names,
        )  # fmt: skip
        write_report(staging, report)
        write_publish_manifest(staging, key)
    return out_dir / folder, report, False
