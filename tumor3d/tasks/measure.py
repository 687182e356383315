"""Adapter of the measure-volume stage (spec section 8)."""

from __future__ import annotations

from tumor3d.geometry.measures import clinical_measures
from tumor3d.imaging.scan import slab_height_mm
from tumor3d.metrics import measure_volumes
from tumor3d.storage.objectstore import open_store
from tumor3d.storage.store import ArtifactRef
from tumor3d.tasks.spec import StageOutput, StageSpec, stage_task

__all__ = ["SPEC", "measure_task"]


@stage_task("measure-volume")
def measure_task(
    scan: ArtifactRef,
    detection: ArtifactRef,
    segmentation: ArtifactRef,
    tumor_mask_slices: ArtifactRef,
    tumor_mask: ArtifactRef,
    mesh: ArtifactRef,
    mesh_simplified: ArtifactRef,
    store_root: str,
) -> StageOutput:
    """Tumour volume by Eq. 7 (with its predicted error), voxels and meshes; RANO diameters."""
    store = open_store(store_root)
    meta = scan.metadata
    det = store.get_table(detection)
    seg = store.get_table(segmentation)
    fine, fine_affine = store.get_volume(tumor_mask)
    dy, dx = meta["pixel_spacing_mm"]
    slab_mm = slab_height_mm(
        meta["slice_step_mm"], meta["slice_thickness_mm"], meta["slice_gap_mm"]
    )
    surface = store.get_mesh(mesh)
    measured = measure_volumes(
        seg["tumor_pixels"].to_numpy(),
        det["abnormal"].to_numpy(dtype=bool),
        fine,
        fine_affine,
        pixel_area_mm2=dy * dx,
        slab_height_mm=slab_mm,
        mesh=surface,
        mesh_simplified=store.get_mesh(mesh_simplified),
    )
    row = measured.to_row()
    slices_mask, _ = store.get_volume(tumor_mask_slices)
    row.update(
        clinical_measures(
            slices_mask, pixel_spacing_mm=(dy, dx), slab_height_mm=slab_mm,
            mesh_vertices=None if surface.is_empty else surface.vertices,
        )  # fmt: skip
    )
    return StageOutput(
        stage="measure-volume", artifacts={"volumes": store.put_table([row])}, values=row
    )


SPEC = StageSpec(
    name="measure-volume",
    task=measure_task,
    entry=measure_volumes,
    config_model=None,
    inputs={
        "scan": "scan",
        "detection": "table",
        "segmentation": "table",
        "tumor_mask_slices": "mask",
        "tumor_mask": "mask",
        "mesh": "mesh",
        "mesh_simplified": "mesh",
    },
    outputs={"volumes": "table"},
)
