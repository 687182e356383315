"""The published files of one patient, declared: :data:`DERIVATIVES`.

One row per file (or family of files) of ``OUT/<patient_id>/``: its default
name, the stage products or run records it is made from, the function that
encodes it, the condition under which it exists and its path under
``--layout bids``. The publisher (:func:`tumor3d.tasks.publish.publish_patient`)
writes the rows in order (:func:`write_derivatives`), the BIDS layout renames
by them (:func:`bids_names`, read by :mod:`tumor3d.storage.bids`), the publish
key holds the code of their encoders (:func:`encoder_modules`) and the
README's outputs table is checked against them (``tests/tasks/test_publish_table.py``).

Sources name a stage product as ``"<stage>.<artifact>"`` (plain strings: this
module, in the storage layer, knows no stage object), or a record of the run:
``metrics`` (the ``metrics.parquet`` row), ``provenance``, ``report``.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from tumor3d.geometry.mesh import Mesh
from tumor3d.storage import nifti
from tumor3d.storage.formats import encode_parquet, encode_ply, encode_stl, encode_vtk_polydata
from tumor3d.storage.patient_outputs import RENDER_ORDER, overlay_png
from tumor3d.storage.refs import ArtifactRef
from tumor3d.storage.report_html import patient_report_html
from tumor3d.storage.slice_table import slice_table
from tumor3d.storage.store import ArtifactStore, source_grid_from_metadata
from tumor3d.storage.viewer import viewer_html

__all__ = [
    "DERIVATIVES",
    "VOLUME_LABELS",
    "VOLUME_METHODS",
    "Condition",
    "Derivative",
    "PatientProducts",
    "bids_names",
    "encoder_modules",
    "write_derivatives",
]

#: Volume columns of metrics.parquet and the method each names.
VOLUME_METHODS: dict[str, str] = {
    "volume_eq7_mm3": "(thickness + gap) x sum of tumour areas over every acquired "
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


@dataclass
class PatientProducts:
    """What one patient's files are made from: the stage products and the run's records.

    Parameters
    ----------
    store : ArtifactStore
        Where the products are.
    artifacts : mapping
        Stage name -> product name -> :class:`ArtifactRef`.
    values : mapping
        Stage name -> its output's values.
    metrics : dict
        The ``metrics.parquet`` row.
    viewer : dict
        ``viewer.html``'s title and colours (keyword arguments of
        :func:`tumor3d.storage.viewer.viewer_html`).
    provenance, report : dict
        ``provenance.json`` and the report's content, once assembled.

    Products are loaded once, when first asked for.
    """

    store: ArtifactStore
    artifacts: Mapping[str, Mapping[str, ArtifactRef]]
    values: Mapping[str, Mapping[str, Any]]
    metrics: dict[str, Any]
    viewer: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    report: dict[str, Any] = field(default_factory=dict)
    _loaded: dict[str, Any] = field(default_factory=dict, repr=False)

    def ref(self, source: str) -> ArtifactRef | None:
        """The product ``"<stage>.<artifact>"``, None if that stage did not make it."""
        stage, _, name = source.partition(".")
        return self.artifacts.get(stage, {}).get(name)

    def _get(self, source: str, how: Callable[[ArtifactRef], Any]) -> Any:
        if source not in self._loaded:
            ref = self.ref(source)
            if ref is None:
                raise KeyError(f"no product {source}")
            self._loaded[source] = how(ref)
        return self._loaded[source]

    def volume(self, source: str) -> tuple[np.ndarray, np.ndarray]:
        """A volume product: ``(array (z, y, x), affine)``, read-only (from memory if kept)."""
        return self._get(source, self.store.load_volume)  # type: ignore[no-any-return]

    def mesh(self, source: str) -> Mesh:
        """A mesh product."""
        return self._get(source, self.store.get_mesh)  # type: ignore[no-any-return]

    def table(self, source: str) -> pd.DataFrame:
        """A table product."""
        return self._get(source, self.store.get_table)  # type: ignore[no-any-return]

    def raw(self, source: str) -> bytes:
        """A product's stored bytes."""
        ref = self.ref(source)
        if ref is None:
            raise KeyError(f"no product {source}")
        return self.store.get_bytes(ref)

    @cached_property
    def grid(self) -> Any:
        """The input's voxel grid (:class:`~tumor3d.imaging.scan.SourceGrid`)."""
        scan = self.ref("ingest-scan.scan")
        assert scan is not None
        return source_grid_from_metadata(scan.metadata)

    @cached_property
    def abnormal_slices(self) -> list[int]:
        """0-based indices of the slices flagged abnormal.

        By the detection, or by the segmentation itself for a method that reads
        every slice (:func:`tumor3d.segmentation.methods.slices_flagged`).
        """
        seg = self.table("segment-tumor.segmentation")
        return seg.loc[seg["flagged"].astype(bool), "slice_index"].astype(int).tolist()


@dataclass(frozen=True)
class Condition:
    """When a file exists: ``text`` says it (the docs), ``holds`` decides it."""

    text: str
    holds: Callable[[PatientProducts], bool]


TUMOUR = Condition("a tumour was found", lambda p: bool(p.metrics["tumour_found"]))
BRAIN_MESH = Condition(
    "the brain mask is not empty", lambda p: not p.mesh("extract-brain-surface.brain_mesh").is_empty
)
PROBABILITY = Condition(
    "the segmentation stored a probability (the learned method)",
    lambda p: p.ref("segment-tumor.tumor_probability") is not None,
)


@dataclass(frozen=True)
class Derivative:
    """One published file, declared.

    Parameters
    ----------
    name : str
        File name in the default layout; ``render_<view>.png`` names a family,
        one file per product of the render-views stage.
    sources : tuple of str
        What it is made from: ``"<stage>.<artifact>"``, ``metrics``,
        ``provenance``, ``report``.
    encode : callable
        :class:`PatientProducts` -> the file's bytes (a family: name -> bytes).
    bids : str
        Its path in ``sub-<label>/`` under ``--layout bids`` (``{label}``; a
        family's ``{view}``); "" keeps the name.
    when : Condition, optional
        Written only when it holds; always when None.
    description : str
        What it holds, in a few words.
    """

    name: str
    sources: tuple[str, ...]
    encode: Callable[[PatientProducts], Any]
    bids: str = ""
    when: Condition | None = None
    description: str = ""

    @property
    def is_family(self) -> bool:
        """One file per product (the renders)."""
        return "<" in self.name


def _source_nifti(source: str, dtype: str | None = None) -> Callable[[PatientProducts], bytes]:
    """A volume product on the input's grid: a mask as uint8 (``dtype`` None), else ``dtype``."""

    def encode(p: PatientProducts) -> bytes:
        array, affine = p.volume(source)
        if dtype is None:
            return nifti.mask_to_source_nifti_bytes(array, p.grid)
        return nifti.volume_to_source_nifti_bytes(array, affine, p.grid, dtype=dtype)

    return encode


def _stored(source: str) -> Callable[[PatientProducts], bytes]:
    """A product's bytes as stored (its encoding is the published one)."""
    return lambda p: p.raw(source)


def _viewer(p: PatientProducts) -> bytes:
    tumour = p.mesh("extract-surface.mesh")
    brain_viewer = p.mesh("extract-brain-surface.brain_mesh_viewer")
    image, affine = p.volume("ingest-scan.scan")
    html = viewer_html(
        image, affine, p.volume("segment-tumor.tumor_mask_slices")[0],
        brain_zyx=p.volume("preprocess.brain_mask")[0],
        tumour_mesh=None if tumour.is_empty else p.mesh("simplify-mesh.mesh"),
        brain_mesh=None if brain_viewer.is_empty else brain_viewer, **p.viewer,
    )  # fmt: skip
    return html.encode("utf-8")


def _overlay(name: str) -> Callable[[PatientProducts], bytes]:
    def encode(p: PatientProducts) -> bytes:
        image, affine = p.volume("preprocess.enhanced")
        brain = p.volume("preprocess.brain_mask")[0]
        tumour = p.volume("segment-tumor.tumor_mask_slices")[0]
        return overlay_png(name, image, affine, brain, tumour, p.abnormal_slices)

    return encode


def _renders(p: PatientProducts) -> dict[str, bytes]:
    return {
        f"{name}{Path(ref.relpath).suffix}": p.store.get_bytes(ref)
        for name, ref in p.artifacts.get("render-views", {}).items()
    }


def _slices(p: PatientProducts) -> bytes:
    table = slice_table(
        p.table("detect-abnormal.detection"), p.table("segment-tumor.segmentation"),
        pixel_area_mm2=p.values["measure-volume"]["pixel_area_mm2"],
        slices_reversed=p.grid.flips[2],
    )  # fmt: skip
    return encode_parquet(table)


def _json(p: PatientProducts) -> bytes:
    return (json.dumps(p.provenance, indent=2) + "\n").encode()


_ANAT = "anat/sub-{label}_"
_FIGURES = "figures/sub-{label}_"

#: Every file of a published patient folder, in the order it is written.
# fmt: off
DERIVATIVES: tuple[Derivative, ...] = (
    Derivative(
        "tumor_mask_slices.nii.gz", ("segment-tumor.tumor_mask_slices",),
        _source_nifti("segment-tumor.tumor_mask_slices"), _ANAT + "desc-tumorslices_mask.nii.gz",
        description="tumour segmentation on the acquired slices, the input's grid",
    ),
    Derivative(
        "tumor_probability.nii.gz", ("segment-tumor.tumor_probability",),
        _source_nifti("segment-tumor.tumor_probability", "float32"),
        _ANAT + "label-tumor_probseg.nii.gz", PROBABILITY,
        "the learned method's lesion probability per voxel, the input's grid",
    ),
    Derivative(
        "brain_mask.nii.gz", ("preprocess.brain_mask",), _source_nifti("preprocess.brain_mask"),
        _ANAT + "desc-brain_mask.nii.gz", description="the brain mask the run used",
    ),
    Derivative(
        "tumor_mask.nii.gz", ("interpolate-slices.tumor_mask",),
        _source_nifti("interpolate-slices.tumor_mask", "uint8"), _ANAT + "desc-tumor_mask.nii.gz",
        description="the tumour after inter-slice interpolation, its finer slice grid",
    ),
    Derivative(
        "tumor.ply", ("extract-surface.mesh",), _stored("extract-surface.mesh"),
        _ANAT + "tumor.ply", TUMOUR, "marching-cubes surface, RAS mm",
    ),
    Derivative(
        "tumor_simplified.ply", ("simplify-mesh.mesh",), _stored("simplify-mesh.mesh"),
        _ANAT + "desc-simplified_tumor.ply", TUMOUR, "the simplified surface, RAS mm",
    ),
    Derivative(
        "brain_mesh.ply", ("extract-brain-surface.brain_mesh",),
        lambda p: encode_ply(p.mesh("extract-brain-surface.brain_mesh")), _ANAT + "brain.ply",
        BRAIN_MESH, "the brain surface around the tumour, RAS mm",
    ),
    Derivative(
        "viewer.html",
        ("ingest-scan.scan", "segment-tumor.tumor_mask_slices", "preprocess.brain_mask",
         "extract-surface.mesh", "simplify-mesh.mesh", "extract-brain-surface.brain_mesh_viewer"),
        _viewer, description="the MR slices with the masks and the surfaces, in a browser",
    ),
    Derivative(
        "tumor_lps.vtk", ("extract-surface.mesh",),
        lambda p: encode_vtk_polydata(p.mesh("extract-surface.mesh"), space="LPS"),
        _ANAT + "desc-lps_tumor.vtk", TUMOUR, "the surface as VTK PolyData, LPS mm",
    ),
    Derivative(
        "tumor.stl", ("extract-surface.mesh",),
        lambda p: encode_stl(p.mesh("extract-surface.mesh"), space="LPS"),
        _ANAT + "desc-lps_tumor.stl", TUMOUR, "the surface as binary STL, LPS mm",
    ),
    Derivative(
        "tumor_simplified.stl", ("simplify-mesh.mesh",),
        lambda p: encode_stl(p.mesh("simplify-mesh.mesh"), space="LPS"),
        _ANAT + "desc-lpssimplified_tumor.stl", TUMOUR, "the simplified surface, STL, LPS mm",
    ),
    *(
        Derivative(
            name,
            ("preprocess.enhanced", "preprocess.brain_mask", "segment-tumor.tumor_mask_slices",
             "detect-abnormal.detection"),
            _overlay(name), f"{_FIGURES}desc-{which}_overlay.png",
            description=f"{which} contour over the preprocessed slices",
        )
        for name, which in (("overlay_tumor.png", "tumor"), ("overlay_brain.png", "brain"))
    ),
    Derivative(
        "render_<view>.png", ("render-views.render_*",), _renders,
        _FIGURES + "desc-{view}_render{suffix}",
        description="the renders: six anatomical views, cut-aways (.png), turntable (.gif)",
    ),
    Derivative(
        "slices.parquet", ("detect-abnormal.detection", "segment-tumor.segmentation"), _slices,
        description="per acquired slice: detection, tumour pixels and area, flagged",
    ),
    Derivative(
        "metrics.parquet", ("metrics",), lambda p: encode_parquet(pd.DataFrame([p.metrics])),
        description="one row: status, volumes by every method, counts, times",
    ),
    Derivative(
        "provenance.json", ("provenance",), _json,
        description="versions, configuration, input digest, stages and their code digests",
    ),
    Derivative(
        "report.html", ("report",), lambda p: patient_report_html(p.report).encode("utf-8"),
        description="the patient's report (after any relayout: its links are the final paths)",
    ),
)
# fmt: on

#: Files the publisher writes once the others are in place (their content names the others).
LAST = ("report.html",)


def _family_files() -> list[tuple[str, str]]:
    """The renders' products and suffixes: the views in the report's order, the turntable."""
    return [(f"render_{v}", ".png") for v in RENDER_ORDER] + [("render_turntable", ".gif")]


def bids_names(label: str) -> dict[str, str]:
    """Default file name -> path in ``sub-<label>/``, for every declared file BIDS renames.

    >>> bids_names("01")["tumor_mask.nii.gz"]
    'anat/sub-01_desc-tumor_mask.nii.gz'
    >>> bids_names("01")["render_cut_axial.png"], bids_names("01")["render_turntable.gif"]
    ('figures/sub-01_desc-cutaxial_render.png', 'figures/sub-01_desc-turntable_render.gif')
    """
    names: dict[str, str] = {}
    for d in DERIVATIVES:
        if not d.bids:
            continue
        if d.is_family:
            for product, suffix in _family_files():
                view = product.removeprefix("render_").replace("_", "")
                path = d.bids.format(label=label, view=view, suffix=suffix)
                names[f"{product}{suffix}"] = path
        else:
            names[d.name] = d.bids.format(label=label)
    return names


def encoder_modules() -> tuple[str, ...]:
    """The modules whose code encodes a published file (the publish key's code roots)."""
    return tuple(sorted({__name__} | {d.encode.__module__ for d in DERIVATIVES}))


def write_derivatives(
    folder: Path, products: PatientProducts, *, skip: tuple[str, ...] = LAST
) -> list[str]:
    """Write every declared file whose condition holds into ``folder``; returns their names.

    ``skip``: names written later (by default ``report.html``, which links the others).
    """
    written: list[str] = []
    for d in DERIVATIVES:
        if d.name in skip or (d.when is not None and not d.when.holds(products)):
            continue
        data = d.encode(products)
        files = data if d.is_family else {d.name: data}
        for name, content in files.items():
            (folder / name).write_bytes(content)
            written.append(name)
    return written


def write_one(folder: Path, products: PatientProducts, name: str) -> str:
    """Write the declared file ``name`` (e.g. ``report.html`` once its content is known)."""
    (d,) = [d for d in DERIVATIVES if d.name == name]
    (folder / name).write_bytes(d.encode(products))
    return name
