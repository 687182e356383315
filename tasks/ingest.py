"""Adapter of the ingest-scan stage: the user's input -> a stored `Scan`."""

from __future__ import annotations

from tumor3d.storage.readers import ReadOptions, read_scan
from tumor3d.storage.readers.handoff import read_noting, take_kept
from tumor3d.tasks.spec import SOURCE, Input, InputSource, StageResult, stage

__all__ = ["SPEC"]


@stage(
    "ingest-scan",
    entry=read_scan,
    inputs={"source": Input(SOURCE, SOURCE)},
    outputs={"scan": "scan"},
)
def ingest_scan(source: InputSource) -> StageResult:
    """Read the user's input (NIfTI, DICOM series, image stack) into a stored `Scan`.

    Keyed and stored by content only: the patient id is neither in the key
    nor in the stored scan or the values (issue 29), so the same file under
    another id is a cache hit and nothing cached names a patient.

    ``header_notes``: the repairs nibabel made to a NIfTI header on reading,
    one note naming the file (informational; never printed by nibabel).

    The scan ``tumor3d run`` read to check the input before starting is
    taken instead of a second read when it is this input, unchanged, read
    with these options (:mod:`tumor3d.storage.readers.handoff`); the key
    does not depend on it.
    """
    options = ReadOptions.of(source)
    # the scan the command line's check read, if it is this input unchanged: one read per run
    kept = take_kept(source.path, options)
    scan, header_notes = (
        kept if kept is not None else read_noting(source.path, options, name=source.name)
    )
    return StageResult(
        artifacts={"scan": scan},
        values={
            "n_slices": scan.n_slices,
            "shape_zyx": list(scan.shape),
            "pixel_spacing_mm": list(scan.pixel_spacing_mm),
            "slice_step_mm": scan.slice_step_mm,
            "slice_thickness_mm": scan.slice_thickness_mm,
            "slice_gap_mm": scan.slice_gap_mm,
            "skipped_files": list(scan.skipped_files),
            "header_notes": header_notes,
            "orientation_stated": scan.orientation_stated,
        },
    )


SPEC = ingest_scan
