"""One coarse Prefect task per pipeline stage.

Each task is a thin adapter: load its input artifacts from the store, call
one function of the pure core (:mod:`tumor3d`), save the results to the
store and return a :class:`StageOutput` of small references. Cache keys
come from :mod:`tasks.caching` only; results are serialised as JSON (never
pickled).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, ClassVar

import numpy as np
from prefect import task
from pydantic import BaseModel, ConfigDict, Field

from storage.store import ArtifactRef, ArtifactStore
from tasks.caching import StageCachePolicy
from tumor3d.config import (
    DetectConfig,
    InterpolateConfig,
    PreprocessConfig,
    RenderConfig,
    SegmentConfig,
    SimplifyConfig,
    SurfaceConfig,
)
from tumor3d.errors import NoSurfaceError
from tumor3d.mesh import Mesh
from tumor3d.scan import slab_height_mm

__all__ = [
    "STAGES",
    "InputSource",
    "StageOutput",
    "detect_task",
    "ingest_task",
    "interpolate_task",
    "measure_task",
    "preprocess_task",
    "render_task",
    "segment_task",
    "simplify_task",
    "stage_modules",
    "surface_task",
]


class StageOutput(BaseModel):
    """What a stage task returns: references and a few scalars, never arrays.

    Parameters
    ----------
    stage : str
        Stage name.
    artifacts : dict of str to ArtifactRef
        The stage's products in the store.
    values : dict
        Small JSON-able results (counts, volumes) for summaries.
    compute_seconds : float
        Wall time of the computation when it actually ran (kept on cache hits).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    stage: str
    artifacts: dict[str, ArtifactRef] = Field(default_factory=dict)
    values: dict[str, Any] = Field(default_factory=dict)
    compute_seconds: float = 0.0


class InputSource(BaseModel):
    """The user's input, identified by content for caching.

    ``path`` is where to read it; ``digest`` (of the file, or of every file of
    a folder, plus sidecars) and ``name`` are what the cache key sees.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    path: str
    name: str
    digest: str
    modality: str
    patient_id: str
    series_uid: str | None = None
    slice_thickness_mm: float | None = None
    slice_gap_mm: float | None = None

    #: Where the input lives does not change what it is.
    __cache_exclude__: ClassVar[frozenset[str]] = frozenset({"path"})


#: Stage name -> the modules whose source is part of its cache key.
STAGES: dict[str, tuple[str, ...]] = {
    "ingest-scan": ("storage.readers", "storage.nifti", "tumor3d.scan"),
    "preprocess": ("tumor3d.preprocess",),
    "detect-abnormal": ("tumor3d.detect",),
    "segment-tumor": ("tumor3d.segment", "tumor3d.detect"),
    "interpolate-slices": ("tumor3d.interpolate",),
    "extract-surface": ("tumor3d.surface", "tumor3d.mesh"),
    "simplify-mesh": ("tumor3d.simplify", "tumor3d.simplify.qem", "tumor3d.surface"),
    "render-views": ("tumor3d.render",),
    "measure-volume": ("tumor3d.metrics", "tumor3d.surface"),
}


def stage_modules(name: str) -> tuple[str, ...]:
    """All modules whose source enters stage ``name``'s code digest (core + adapters)."""
    return (*STAGES[name], "tasks.stages", "storage.store", "storage.formats")


def _stage_task(name: str) -> Callable[[Callable[..., StageOutput]], Any]:
    """Decorate a stage function as a cached Prefect task named ``name``."""
    modules = stage_modules(name)

    def decorate(fn: Callable[..., StageOutput]) -> Any:
        def timed(*args: Any, **kwargs: Any) -> StageOutput:
            t0 = time.perf_counter()
            out = fn(*args, **kwargs)
            return out.model_copy(update={"compute_seconds": time.perf_counter() - t0})

        timed.__name__ = fn.__name__
        timed.__qualname__ = fn.__qualname__
        timed.__doc__ = fn.__doc__
        timed.__module__ = fn.__module__
        timed.__wrapped__ = fn  # type: ignore[attr-defined]
        return task(
            name=name,
            task_run_name=name,
            cache_policy=StageCachePolicy(stage=name, modules=modules),
            persist_result=True,
            result_serializer="json",
            retries=0,
        )(timed)

    return decorate


@_stage_task("ingest-scan")
def ingest_task(source: InputSource, store_root: str) -> StageOutput:
    """Read the user's input (NIfTI, DICOM series, image stack) into a stored `Scan`."""
    from storage.readers import read_scan

    scan = read_scan(
        source.path,
        modality=source.modality,
        patient_id=source.patient_id,
        series_uid=source.series_uid,
        slice_thickness_mm=source.slice_thickness_mm,
        slice_gap_mm=source.slice_gap_mm,
    )
    ref = ArtifactStore(store_root).put_scan(scan)
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
        },
    )


@_stage_task("preprocess")
def preprocess_task(scan: ArtifactRef, config: PreprocessConfig, store_root: str) -> StageOutput:
    """Median, unsharp masking, equalisation and skull removal (spec section 1)."""
    from tumor3d.preprocess import preprocess_volume

    store = ArtifactStore(store_root)
    image, affine = store.get_volume(scan)
    result = preprocess_volume(image, **config.model_dump())
    return StageOutput(
        stage="preprocess",
        artifacts={
            "enhanced": store.put_volume(result.enhanced, affine, dtype="uint8"),
            "brain_mask": store.put_volume(result.brain_mask, affine, kind="mask"),
        },
        values={"brain_voxels": int(np.count_nonzero(result.brain_mask))},
    )


@_stage_task("detect-abnormal")
def detect_task(
    enhanced: ArtifactRef, brain_mask: ArtifactRef, config: DetectConfig, store_root: str
) -> StageOutput:
    """Abnormal-slice detection by counting histogram modes (spec section 2)."""
    from tumor3d.detect import detect_abnormal_slices

    store = ArtifactStore(store_root)
    image, _ = store.get_volume(enhanced)
    brain, _ = store.get_volume(brain_mask)
    detection = detect_abnormal_slices(image, brain, **config.model_dump())
    abnormal = np.flatnonzero(detection.abnormal)
    return StageOutput(
        stage="detect-abnormal",
        artifacts={"detection": store.put_table(detection.to_records())},
        values={"n_abnormal_slices": int(abnormal.size), "abnormal_slices": abnormal.tolist()},
    )


@_stage_task("segment-tumor")
def segment_task(
    scan: ArtifactRef,
    enhanced: ArtifactRef,
    brain_mask: ArtifactRef,
    detection: ArtifactRef,
    config: SegmentConfig,
    store_root: str,
) -> StageOutput:
    """Wavelet + histogram fuzzy c-means tumour segmentation (spec section 3)."""
    from tumor3d.detect import SliceDetection
    from tumor3d.segment import segment_tumor

    store = ArtifactStore(store_root)
    image, affine = store.get_volume(enhanced)
    brain, _ = store.get_volume(brain_mask)
    det = SliceDetection.from_records(store.get_table(detection).to_dict("records"))
    result = segment_tumor(
        image, brain, det, modality=scan.metadata["modality"], **config.model_dump()
    )
    return StageOutput(
        stage="segment-tumor",
        artifacts={
            "tumor_mask_slices": store.put_volume(result.tumor_mask, affine, kind="mask"),
            "segmentation": store.put_table(result.to_records()),
        },
        values={
            "tumor_pixels_total": int(np.sum(result.tumor_pixels)),
            "n_tumor_slices": int(np.count_nonzero(result.tumor_pixels)),
        },
    )


@_stage_task("interpolate-slices")
def interpolate_task(
    scan: ArtifactRef, tumor_mask_slices: ArtifactRef, config: InterpolateConfig, store_root: str
) -> StageOutput:
    """Shape-based interpolation of the missing slices (spec section 4)."""
    from tumor3d.interpolate import interpolate_stack, slices_between_auto

    store = ArtifactStore(store_root)
    masks, affine = store.get_volume(tumor_mask_slices)
    m = config.slices_between
    if m is None:
        m = slices_between_auto(
            scan.metadata["slice_step_mm"], tuple(scan.metadata["pixel_spacing_mm"])
        )
    stack = interpolate_stack(
        masks, method=config.method, slices_between=m, end_caps=config.end_caps
    )
    fine_affine = stack.fine_affine(affine)
    return StageOutput(
        stage="interpolate-slices",
        artifacts={"tumor_mask": store.put_volume(stack.mask, fine_affine, kind="mask")},
        values={
            "slices_between": int(stack.slices_between),
            "n_fine_slices": int(stack.mask.shape[0]),
            "n_interpolated_slices": int(np.count_nonzero(stack.interpolated)),
        },
    )


@_stage_task("extract-surface")
def surface_task(tumor_mask: ArtifactRef, config: SurfaceConfig, store_root: str) -> StageOutput:
    """Marching cubes on the zero-padded interpolated mask (spec section 5)."""
    from tumor3d.surface import extract_surface

    store = ArtifactStore(store_root)
    mask, affine = store.get_volume(tumor_mask)
    try:
        mesh = extract_surface(mask, affine, **config.model_dump())
    except NoSurfaceError:
        mesh = Mesh(np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64))
    return StageOutput(
        stage="extract-surface",
        artifacts={"mesh": store.put_mesh(mesh)},
        values={
            "faces": mesh.n_faces,
            "vertices": mesh.n_vertices,
            "watertight": _closed(mesh),
        },
    )


@_stage_task("simplify-mesh")
def simplify_task(mesh: ArtifactRef, config: SimplifyConfig, store_root: str) -> StageOutput:
    """Edge-collapse simplification to F_target faces (spec section 6).

    A mesh too small to simplify (F_target below 4 faces) is passed through
    unchanged and flagged, rather than failing the patient.
    """
    from tumor3d.simplify import simplify_mesh, target_face_count

    store = ArtifactStore(store_root)
    source = store.get_mesh(mesh)
    target = target_face_count(source.n_faces, config.reduction_percent)
    values: dict[str, Any] = {"faces_target": target, "simplified": False}
    simplified = source
    if not source.is_empty and target >= _MIN_SIMPLIFIED_FACES:
        simplified, info = simplify_mesh(source, **config.model_dump(), return_info=True)
        values.update(simplified=True, watertight=bool(info["watertight"]))
    else:
        values["watertight"] = _closed(source)
    values["faces"] = simplified.n_faces
    return StageOutput(
        stage="simplify-mesh", artifacts={"mesh": store.put_mesh(simplified)}, values=values
    )


def _closed(mesh: Mesh) -> bool:
    """True for a non-empty watertight mesh (an empty mesh encloses nothing)."""
    from tumor3d.surface import is_watertight

    return bool(not mesh.is_empty and is_watertight(mesh))


#: The smallest closed triangle mesh (a tetrahedron) has 4 faces.
_MIN_SIMPLIFIED_FACES = 4


@_stage_task("render-views")
def render_task(mesh: ArtifactRef, config: RenderConfig, store_root: str) -> StageOutput:
    """Shaded renders of the surface: anatomical views, cut-aways, turntable (spec section 7)."""
    from tumor3d.render import render_views, turntable_gif

    store = ArtifactStore(store_root)
    surface = store.get_mesh(mesh)
    artifacts: dict[str, ArtifactRef] = {}
    values: dict[str, Any] = {"n_views": 0}
    if not surface.is_empty:
        result = render_views(surface, **config.model_dump())
        for name, rgb in result.images.items():
            artifacts[f"render_{name}"] = store.put_png(rgb, extra={"view": name})
        if result.turntable:
            artifacts["render_turntable"] = store.put_bytes(
                turntable_gif(result.turntable), kind="gif", suffix=".gif"
            )
        values = {
            "n_views": len(artifacts),
            "renderer": result.info["renderer"],
            "fallback_reason": result.info["fallback_reason"],
        }
    return StageOutput(stage="render-views", artifacts=artifacts, values=values)


@_stage_task("measure-volume")
def measure_task(
    scan: ArtifactRef,
    detection: ArtifactRef,
    segmentation: ArtifactRef,
    tumor_mask: ArtifactRef,
    mesh: ArtifactRef,
    mesh_simplified: ArtifactRef,
    store_root: str,
) -> StageOutput:
    """Tumour volume by Eq. 7, by voxel counting and enclosed by the meshes (spec section 8)."""
    from tumor3d.metrics import mm3_to_ml, volume_eq7_mm3, volume_voxel_mm3, voxel_volume_mm3
    from tumor3d.surface import mesh_volume_mm3

    store = ArtifactStore(store_root)
    meta = scan.metadata
    det = store.get_table(detection)
    seg = store.get_table(segmentation)
    fine, fine_affine = store.get_volume(tumor_mask)
    dy, dx = meta["pixel_spacing_mm"]
    slab_mm = slab_height_mm(
        meta["slice_step_mm"], meta["slice_thickness_mm"], meta["slice_gap_mm"]
    )
    tumor_pixels = seg["tumor_pixels"].to_numpy()
    # Eq. 7 sums the abnormal slices; a slice where segmentation found the
    # tumour's tip (beyond detection's abnormal slices) is abnormal too.
    abnormal = det["abnormal"].to_numpy(dtype=bool) | (tumor_pixels > 0)
    eq7 = volume_eq7_mm3(
        tumor_pixels,
        abnormal,
        pixel_area_mm2=dy * dx,
        slab_height_mm=slab_mm,
    )
    voxel = volume_voxel_mm3(fine, voxel_volume_mm3=voxel_volume_mm3(fine_affine))
    volumes = {"volume_eq7_mm3": eq7, "volume_voxel_mm3": voxel}
    for key, ref in (("volume_mesh_mm3", mesh), ("volume_mesh_simplified_mm3", mesh_simplified)):
        m = store.get_mesh(ref)
        volumes[key] = 0.0 if m.is_empty else float(mesh_volume_mm3(m))
    row: dict[str, Any] = {}
    for key, value in volumes.items():
        row[key] = float(value)
        row[key.replace("_mm3", "_ml")] = float(mm3_to_ml(value))
    row.update(
        n_slices=int(len(det)),
        n_abnormal_slices=int(det["abnormal"].sum()),
        n_tumor_slices=int(np.count_nonzero(tumor_pixels)),
        slab_height_mm=float(slab_mm),
        pixel_area_mm2=float(dy * dx),
    )
    return StageOutput(
        stage="measure-volume", artifacts={"volumes": store.put_table([row])}, values=row
    )
