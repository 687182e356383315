"""Adapter of the ingest-scan stage: the user's input -> a stored `Scan`."""

from __future__ import annotations

from tumor3d.storage.objectstore import open_store
from tumor3d.storage.readers import read_scan
from tumor3d.storage.readers.nifti import nibabel_header_notes
from tumor3d.tasks.spec import InputSource, StageOutput, StageSpec, stage_task

__all__ = ["SPEC", "ingest_task"]


@stage_task("ingest-scan")
def ingest_task(source: InputSource, store_root: str) -> StageOutput:
    """Read the user's input (NIfTI, DICOM series, image stack) into a stored `Scan`.

    Keyed and stored by content only: the patient id is neither in the key
    nor in the stored scan or the values (issue 29), so the same file under
    another id is a cache hit and nothing cached names a patient.

    ``header_notes``: the repairs nibabel made to a NIfTI header on reading,
    one note naming the file (informational; never printed by nibabel).
    """
    with nibabel_header_notes(source.name) as header_notes:
        scan = read_scan(
            source.path,
            modality=source.modality,
            patient_id=source.patient_id,
            series_uid=source.series_uid,
            slice_thickness_mm=source.slice_thickness_mm,
            slice_gap_mm=source.slice_gap_mm,
            skip_unreadable=source.skip_unreadable,
            max_voxels=source.max_voxels,
        )
    ref = open_store(store_root).put_scan(scan)
    return StageOutput(
        stage="ingest-scan",
        artifacts={"scan": ref},
        values={
            "n_slices": scan.n_slices,
            "shape_zyx": list(scan.shape),
            "pixel_spacing_mm": list(scan.pixel_spacing_mm),
            "slice_step_mm": scan.slice_step_mm,
            "slice_thickness_mm": scan.slice_thickness_mm,
            "slice_gap_mm": scan.slice_gap_mm,
            "skipped_files": list(scan.skipped_files),
            "header_notes": header_notes,
        },
    )


SPEC = StageSpec(
    name="ingest-scan",
    task=ingest_task,
    entry=read_scan,
    config_model=None,
    inputs={"source": "source"},
    outputs={"scan": "scan"},
)
