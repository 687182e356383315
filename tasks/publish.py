"""Publishing one patient: its metrics row, notes, publish key and published folder.

The files are declared in :mod:`tumor3d.storage.derivatives` (name, sources,
encoder, condition, BIDS name); this module assembles what they are made from
and swaps the folder into place (:mod:`tumor3d.storage.publish`). It lives in
the tasks layer, not beside the table in storage, because it reads the stage
declarations (:mod:`tumor3d.tasks.stages`: the ``metrics.parquet`` columns
each stage declares, each stage's code digest) and the one code digest of
:mod:`tumor3d.tasks.caching`, which the storage layer may not import.
"""

from __future__ import annotations

import hashlib
import json
import tempfile
from pathlib import Path
from typing import Any

from tumor3d.config import PipelineConfig
from tumor3d.errors import InputError
from tumor3d.imaging.affine import slice_overlap_note
from tumor3d.imaging.orientation import slice_order_note
from tumor3d.imaging.scan import SourceGrid
from tumor3d.learned.shipped import MODEL_IDENTITY_KEYS
from tumor3d.metrics import EQ7_SLICE_RULES
from tumor3d.segmentation.review import Review, brain_mask_run_notes, review_status
from tumor3d.segmentation.review import run_notes as review_notes
from tumor3d.storage import bids
from tumor3d.storage.brain_mask import GivenBrainMask
from tumor3d.storage.derivatives import (
    VOLUME_METHODS,
    PatientProducts,
    encoder_modules,
    write_derivatives,
    write_one,
)
from tumor3d.storage.given_segmentation import GivenSegmentation
from tumor3d.storage.inputs import input_location
from tumor3d.storage.objectstore import is_url
from tumor3d.storage.patient_outputs import join_notes, patient_report_data, split_notes
from tumor3d.storage.provenance import build_provenance, versions
from tumor3d.storage.publish import (
    PUBLISH_MANIFEST,
    check_output_not_input,
    check_same_input,
    clean_stale_staging,
    published_is_current,
    staged_folder,
    write_publish_manifest,
)
from tumor3d.storage.remote_publish import publish_folder
from tumor3d.storage.store import ArtifactStore, canonical_dumps, source_grid_from_metadata
from tumor3d.storage.viewer import ASSETS_DIR, write_viewer_assets
from tumor3d.tasks import stages
from tumor3d.tasks.runner import StageRun
from tumor3d.tasks.spec import InputSource, StageOutput

__all__ = [
    "REVIEW_COLUMNS",
    "brain_mask_note",
    "check_layout_destination",
    "config_digest",
    "given_inputs",
    "grid_orientation",
    "metrics_row",
    "publish_key",
    "publish_patient",
    "publish_results",
    "publisher_code_digest",
    "run_notes",
    "run_review",
]

#: ``metrics.parquet``'s columns of when to check (:func:`metrics_row`): needs_review,
#: the review's reasons, the segmentation's own quality score (a method that scores
#: itself); ``evaluation.parquet`` copies them (:mod:`tumor3d.flows.evaluate`).
REVIEW_COLUMNS = ("needs_review", "review_reasons", "segmentation_quality_score")


def config_digest(cfg: PipelineConfig) -> str:
    """SHA-256 of the canonical JSON of a whole configuration."""
    return hashlib.sha256(canonical_dumps(cfg.model_dump(mode="json")).encode()).hexdigest()


def given_inputs(
    brain_mask: GivenBrainMask | None, segmentation: GivenSegmentation | None
) -> list[str]:
    """The given mask files (never inside the output folder, never modified)."""
    return [m.path for m in (brain_mask, segmentation) if m is not None]


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
    bids.check_dataset_root(out_dir, [source.path] + given_inputs(brain_mask, segmentation))


def brain_mask_note(mask: GivenBrainMask) -> str:
    """The note a run with a given brain mask carries (summary, metrics, provenance)."""
    return f"brain mask given ({mask.name}, SHA-256 {mask.sha256[:12]}...): no skull removal"


def run_notes(
    outputs: dict[str, StageOutput],
    brain_mask: GivenBrainMask | None = None,
    segmentation: GivenSegmentation | None = None,
    *,
    modality_default: bool = False,
) -> tuple[list[str], list[str]]:
    """The run's notes (summary, metrics, provenance) and those that doubt the result.

    :func:`tumor3d.segmentation.review.run_notes` on the stages' values: the doubts make
    the status ``check`` (:func:`tumor3d.segmentation.review.review_status`). A given
    segmentation adds an informational note (``segmentation: given (FILE, ...)``),
    as do nibabel's repairs of the input's NIfTI header (the ingest-scan stage's
    ``header_notes``; the note that the header states no orientation,
    :data:`tumor3d.segmentation.review.ORIENTATION_UNSTATED`, doubts), which end the
    slice numbers count from (:func:`tumor3d.imaging.scan.slice_order_note`) and, with
    ``modality_default``, the modality taken by default (nothing named it), which doubts:
    the sequence decides the method and what it segments (a FLAIR run as T2 gave twice
    its tumour's volume, a user audit), so a result on an assumed one asks for a check.

    The stages' outputs are read by their declared names (``outputs``: stage name ->
    output), the values no declaration lists as a ``metrics.parquet`` column.
    """
    seg = outputs["segment-tumor"].values
    ingest = outputs["ingest-scan"]
    scan = ingest.artifacts.get("scan")
    notes, doubts = review_notes(
        tumour_found=outputs["extract-surface"].values["faces"] > 0,
        caveats=seg.get("caveats") or [],
        skipped_files=ingest.values.get("skipped_files") or [],
        brain_mask_note=None if brain_mask is None else brain_mask_note(brain_mask),
        **brain_mask_run_notes(outputs["preprocess"].values, seg.get("segment_method")),
        # nibabel's repairs of a NIfTI header (tumor3d.tasks.ingest), never printed, and
        # slices thicker than their step (tumor3d.imaging.affine.slice_overlap_note)
        header_notes=[*(ingest.values.get("header_notes") or []), *_overlap(ingest.values)],
        slice_order_note=None
        if scan is None
        else slice_order_note(source_grid_from_metadata(scan.metadata)),
    )
    if segmentation is not None:
        notes.append(segmentation.note())
    if modality_default:
        mod = str(seg.get("modality", "t2"))
        assumed = (
            f"modality: {mod} by default (nothing named it: no option, manifest value or "
            f"sidecar); give the modality if the scan is not {mod.upper()}"
        )
        notes.append(assumed)
        doubts.append(assumed)
    return notes, doubts


def _overlap(values: dict[str, Any]) -> list[str]:
    """The ingest stage's slice geometry's overlap note, as a list (empty: none or unknown)."""
    keys = ("slice_step_mm", "slice_thickness_mm", "slice_gap_mm")
    if any(values.get(k) is None for k in keys):
        return []
    note = slice_overlap_note(*(float(values[k]) for k in keys))
    return [] if note is None else [note]


def run_review(outputs: dict[str, StageOutput], doubts: list[str]) -> Review:
    """The run's status and why: its ``doubts`` (:func:`run_notes`) and the segmentation's own.

    :func:`tumor3d.segmentation.review.review_status` with the segment-tumor stage's
    values (``needs_review``, ``review_reasons``, ``quality_score`` of a method that
    reviews itself).
    """
    return review_status(doubts, segmentation=outputs["segment-tumor"].values)


def metrics_row(
    outputs: dict[str, StageOutput],
    runs: list[StageRun],
    pid: str,
    flow_seconds: float,
    notes: list[str],
    review: Review,
) -> dict[str, Any]:
    """The ``metrics.parquet`` row: the review, every stage's declared columns, notes, times.

    The stage columns are those the stages declare
    (:func:`tumor3d.tasks.stages.metric_columns`), in stage order.
    """
    row: dict[str, Any] = {"patient_id": pid}
    # ok or check (a failed run publishes no metrics); tumor3d.segmentation.review decides
    row["status"] = review.status
    needs, reasons, score = REVIEW_COLUMNS
    row[needs] = review.needs_review
    row[reasons] = join_notes(review.reasons)
    if review.quality_score is not None:  # a segmentation method that scores itself
        row[score] = float(review.quality_score)
    row.update(stages.metric_columns(outputs))
    row["tumour_found"] = row["faces_mc"] > 0
    row["notes"] = join_notes(notes)
    for r in runs:
        key = r.stage.replace("-", "_")
        row[f"time_{key}_s"] = float(r.compute_seconds)
        row[f"cached_{key}"] = bool(r.cached)
    row["time_flow_s"] = float(flow_seconds)
    return row


def publisher_code_digest() -> str:
    """The code digest of this module and the encoders of the published files.

    :func:`tumor3d.tasks.caching.code_digest` of this module's closure and of
    the modules of the table's encoders
    (:func:`tumor3d.storage.derivatives.encoder_modules`): syntax trees, so a
    comment or docstring does not republish; with the store codecs, which
    encode published files too.
    """
    from tumor3d.tasks.caching import code_digest

    return code_digest((__name__, *encoder_modules()), include_codecs=True)


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
    code digest, the publisher's code (:func:`publisher_code_digest`) and
    the recorded package versions, and a given brain mask's name and
    SHA-256 (recorded in provenance). Equal keys mean the folder's content
    would be the same, except the run's own times and cache flags.
    """
    doc: dict[str, Any] = {
        "source": source.model_dump(mode="json", exclude={"path"}),
        "outputs": {name: out.content_digest() for name, out in sorted(outputs.items())},
        "config_sha256": config_digest(cfg),
        "stage_code": stages.code_digests(),
        "publisher": publisher_code_digest(),
        "versions": versions(),
    }
    if brain_mask is not None:
        doc["brain_mask"] = brain_mask.provenance()
    if segmentation is not None:
        doc["segmentation"] = segmentation.provenance()
    if layout != "default":  # the default layout's keys stay those published before
        doc["layout"] = layout
    return hashlib.sha256(canonical_dumps(doc).encode()).hexdigest()


def grid_orientation(grid: SourceGrid) -> dict[str, str]:
    """Axis codes (nibabel's) of the input file's voxel axes and of the Scan's ``x, y, z``.

    >>> import numpy as np
    >>> las = SourceGrid(shape=(4, 4, 3), affine=np.diag([-1.0, 1.0, 5.0, 1.0]),
    ...                  flips=(False, True, False))
    >>> grid_orientation(las)
    {'stored': 'LAS', 'read_as': 'LPS'}
    """
    from nibabel.orientations import aff2axcodes

    stored = [str(c) for c in aff2axcodes(grid.affine)]
    opposite = {"L": "R", "R": "L", "A": "P", "P": "A", "S": "I", "I": "S"}
    read = [
        opposite[stored[a]] if flipped else stored[a]
        for a, flipped in zip(grid.axes, grid.flips, strict=True)
    ]
    return {"stored": "".join(stored), "read_as": "".join(read)}


def _provenance(
    source: InputSource,
    outputs: dict[str, StageOutput],
    runs: list[StageRun],
    metrics: dict[str, Any],
    cfg: PipelineConfig,
    brain_mask: GivenBrainMask | None,
    segmentation: GivenSegmentation | None,
    grid: SourceGrid,
) -> dict[str, Any]:
    """The ``provenance.json`` record (:func:`tumor3d.storage.provenance.build_provenance`).

    ``input.orientation``: the axis codes of the file's voxel order and of the
    working orientation the methods read (:func:`grid_orientation`).
    """
    rule = str(metrics.get("eq7_slice_rule", "segmented"))
    input_info = {
        "name": source.name,
        "digest_sha256": source.digest,
        "location_sha256": input_location(source.path),
    }
    input_info.update(modality=source.modality, patient_id=source.patient_id)
    scanned = outputs["ingest-scan"].values
    # the slab as read: the step from the affine, the thickness stated by the option or
    # the file's metadata (else the step), the gap what is left (negative: overlapping)
    input_info["slices"] = {
        f"{k}_mm": scanned.get(f"slice_{k}_mm") for k in ("step", "thickness", "gap")
    }
    input_info["orientation"] = {
        **grid_orientation(grid),
        # False: a folder of 2-D slices, or a NIfTI header without orientation (assumed)
        "stated": bool(scanned.get("orientation_stated", True)),
    }
    code = stages.code_digests()
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
    seg = outputs["segment-tumor"].values
    provenance["segmentation"] = (
        {
            "given": False,
            "method": seg.get("segment_method"),
            # the learned method's model: its name and digest (absent for the others), and
            # the U-Net's file and SHA-256 where its probability was averaged with the forest's
            **{k: seg[k] for k in MODEL_IDENTITY_KEYS if k in seg},
        }
        if segmentation is None
        else segmentation.provenance()
    )
    return provenance


def _current_report(
    folder: Path,
    products: PatientProducts,
    runs: list[StageRun],
    label: str | None = None,
) -> dict[str, Any]:
    """The report content of an up-to-date published folder, for this run's artifacts.

    ``label``: a BIDS folder (``sub-<label>``), whose files are found under their BIDS paths.
    """
    files = sorted(f.name for f in folder.iterdir() if f.is_file() and f.name != PUBLISH_MANIFEST)
    names = None
    if label is not None:
        names = {k: v for k, v in bids.bids_names(label).items() if (folder / v).is_file()}
        files += list(names)
    return patient_report_data(
        products.metrics, stage_runs=[r.model_dump() for r in runs],
        abnormal_slices=products.abnormal_slices, files=files,
        provenance=json.loads((folder / "provenance.json").read_text()), names=names,
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
    """Write the patient's files to a staging folder, then swap it into ``out_dir/<id>``.

    The files are those of :data:`tumor3d.storage.derivatives.DERIVATIVES` whose
    condition holds. Skipped when every stage was a cache hit (none repaired) and
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
    inputs = [source.path] + given_inputs(brain_mask, segmentation)
    check_output_not_input(out_dir / folder, inputs)
    key = publish_key(source, outputs, cfg, brain_mask, segmentation, layout)
    write_viewer_assets(out_dir)  # viewer.html's script, once per output folder
    raw = bids.raw_source(source.path) if label is not None else None
    if label is not None:
        bids.check_dataset_root(out_dir, inputs)
        bids.write_dataset_files(out_dir, None if raw is None else raw[0])
    products = PatientProducts(
        store,
        artifacts={name: out.artifacts for name, out in outputs.items()},
        values={name: out.values for name, out in outputs.items()},
        metrics=metrics,
        viewer={
            "title": f"tumor3d: {pid}",
            "tumor_color_rgb": cfg.render.color_rgb,
            "brain_color_rgb": cfg.render.brain_color_rgb,
            "brain_opacity": cfg.render.brain_opacity,
        },
    )
    reused = all(r.cached and not r.repaired for r in runs)
    if reused and published_is_current(out_dir / folder, key):
        clean_stale_staging(out_dir, folder)
        try:
            report = _current_report(out_dir / folder, products, runs, label)
        except (OSError, ValueError):  # changed since the check: publish again
            pass
        else:
            return out_dir / folder, report, True
    same_input = None
    if source.id_derived:  # checked again right before the swap: a concurrent run's folder
        location = input_location(source.path)

        def same_input(final: Path) -> None:
            check_same_input(final, source.digest, location=location)

    products.provenance = _provenance(
        source, outputs, runs, metrics, cfg, brain_mask, segmentation, products.grid
    )
    with staged_folder(out_dir, folder, check=same_input) as staging:
        files = write_derivatives(staging, products)
        names = None
        if label is not None:  # BIDS names, sidecars and GIFTI surfaces (tumor3d.storage.bids)
            names = bids.relayout(
                staging, label, files, metrics=metrics, volume_methods=VOLUME_METHODS,
                raw_uri=None if raw is None else f"bids:raw:{raw[1]}",
            )  # fmt: skip
        products.report = patient_report_data(
            metrics, stage_runs=[r.model_dump() for r in runs],
            abnormal_slices=products.abnormal_slices, files=files,
            provenance=products.provenance, names=names,
        )  # fmt: skip
        write_one(staging, products, "report.html")
        write_publish_manifest(staging, key)
    return out_dir / folder, products.report, False


def publish_results(
    store: ArtifactStore,
    out_dir: str | Path,
    source: InputSource,
    outputs: dict[str, StageOutput],
    runs: list[StageRun],
    metrics: dict[str, Any],
    cfg: PipelineConfig,
    brain_mask: GivenBrainMask | None = None,
    segmentation: GivenSegmentation | None = None,
    *,
    layout: str = "default",
) -> tuple[str | Path, dict[str, Any], bool]:
    """:func:`publish_patient` into a local ``out_dir``, or staged locally and uploaded.

    An object store (``s3://...``) receives the staged folder through
    :func:`tumor3d.storage.remote_publish.publish_folder` (an unchanged upload
    skipped; with every stage reused, a folder of the same key kept) and the
    viewer's shared script beside it. Returns where the folder is, the
    report's content and whether it was already up to date.
    """
    if not is_url(out_dir):
        return publish_patient(
            store, Path(out_dir), source, outputs, runs, metrics, cfg, brain_mask, segmentation,
            layout=layout,
        )  # fmt: skip
    base = str(out_dir).rstrip("/")
    with tempfile.TemporaryDirectory(prefix="tumor3d-publish-") as tmp:
        staged, report, _ = publish_patient(
            store, Path(tmp), source, outputs, runs, metrics, cfg, brain_mask, segmentation
        )
        reused = all(r.cached and not r.repaired for r in runs)
        out_path = publish_folder(staged, f"{base}/{source.patient_id}", reuse=reused)
        # the viewer's shared script (unchanged bytes are read back, not uploaded)
        publish_folder(Path(tmp) / ASSETS_DIR, f"{base}/{ASSETS_DIR}")
    return out_path, report, False
