"""Adapter of the measure-volume stage (spec section 8)."""

from __future__ import annotations

import pandas as pd

from tumor3d.geometry.measures import clinical_measures
from tumor3d.geometry.mesh import Mesh
from tumor3d.imaging.affine import slab_height_mm
from tumor3d.metrics import measure_volumes
from tumor3d.tasks.kinds import Artifact, Volume
from tumor3d.tasks.spec import ALL_VALUES, Input, StageResult, stage

__all__ = ["SPEC"]


@stage(
    "measure-volume",
    entry=measure_volumes,
    inputs={
        "scan": Input("scan", "ingest-scan.scan", load=False),  # its slice geometry
        "segmentation": Input("table", "segment-tumor.segmentation"),
        "tumor_mask_slices": Input("mask", "segment-tumor.tumor_mask_slices"),
        "tumor_mask": Input("mask", "interpolate-slices.tumor_mask"),
        "mesh": Input("mesh", "extract-surface.mesh"),
        "mesh_simplified": Input("mesh", "simplify-mesh.mesh"),
    },
    outputs={"volumes": "table"},
    # the volumes by every method (tumor3d.metrics.VolumeMeasurement.to_row) and the
    # clinical measures (tumor3d.geometry.measures.clinical_measures), under their names
    metrics=ALL_VALUES,
)
def measure_volume(
    scan: Artifact,
    segmentation: pd.DataFrame,
    tumor_mask_slices: Volume,
    tumor_mask: Volume,
    mesh: Mesh,
    mesh_simplified: Mesh,
) -> StageResult:
    """Tumour volume by Eq. 7 (with its predicted error), voxels and meshes; RANO diameters."""
    meta = scan.metadata
    dy, dx = meta["pixel_spacing_mm"]
    slab_mm = slab_height_mm(
        meta["slice_step_mm"], meta["slice_thickness_mm"], meta["slice_gap_mm"]
    )
    measured = measure_volumes(
        segmentation["tumor_pixels"].to_numpy(),
        segmentation["flagged"].to_numpy(dtype=bool),  # the method's (slices_flagged)
        tumor_mask.array,
        tumor_mask.affine,
        pixel_area_mm2=dy * dx,
        slab_height_mm=slab_mm,
        mesh=mesh,
        mesh_simplified=mesh_simplified,
    )
    row = measured.to_row()
    row.update(
        clinical_measures(
            tumor_mask_slices.array,
            pixel_spacing_mm=(dy, dx),
            slab_height_mm=slab_mm,
            mesh_vertices=None if mesh.is_empty else mesh.vertices,
        )
    )
    # the slab's parts as read (a negative gap: overlapping slices), beside slab_height_mm
    row.update(slice_thickness_mm=meta["slice_thickness_mm"], slice_gap_mm=meta["slice_gap_mm"])
    return StageResult(artifacts={"volumes": [row]}, values=row)


SPEC = measure_volume
