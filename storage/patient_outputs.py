"""Writers of a patient's derived outputs: overlays, viewer files and ``report.html``.

Called through the table of published files (:mod:`tumor3d.storage.derivatives`)
with what it read from the artifact store; every file goes into the publishing staging folder (so
nothing is half-written under the final name). The report's content is
assembled by :func:`patient_report_data` from the metrics row, the stage
runs and the list of files actually written, so every link of
``report.html`` points at a file beside it (relative links: the folder can
be moved).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from tumor3d.geometry.mesh import Mesh
from tumor3d.storage.formats import encode_ply, encode_png, encode_stl, encode_vtk_polydata
from tumor3d.storage.report_html import patient_report_html
from tumor3d.storage.viewer import viewer_html
from tumor3d.visual.overlay import overlay_mosaic

__all__ = [
    "NOTES_SEPARATOR",
    "OVERLAYS",
    "OVERLAY_CONTOUR_PX",
    "OVERLAY_MARGIN_VOXELS",
    "OVERLAY_TILE_PX",
    "RENDER_ORDER",
    "join_notes",
    "method_words",
    "orientation_words",
    "overlay_png",
    "patient_report_data",
    "split_notes",
    "write_overlays",
    "write_report",
    "write_surface_files",
]

#: The separator of a run's notes in the ``notes`` column of ``metrics.parquet``.
NOTES_SEPARATOR = "; "


def join_notes(notes: Iterable[str]) -> str:
    """A run's notes as one string (``metrics.parquet``); :func:`split_notes` inverts it.

    A separator inside a note (a file name, a sentence) becomes ``", "``, so
    that the note comes back whole and not as two.

    >>> split_notes(join_notes(["a; b", "c"]))
    ['a, b', 'c']
    """
    return NOTES_SEPARATOR.join(str(n).replace(NOTES_SEPARATOR, ", ") for n in notes if str(n))


def split_notes(text: Any) -> list[str]:
    """The notes of :func:`join_notes`'s string; [] for an empty or missing value."""
    if not isinstance(text, str):
        return []
    return [n for n in text.split(NOTES_SEPARATOR) if n]


#: Overlay files and their captions.
OVERLAYS: dict[str, str] = {
    "overlay_tumor.png": "tumour contour over the preprocessed slices (abnormal slices framed)",
    "overlay_brain.png": "brain-mask contour (skull removal) over the preprocessed slices",
}

#: Overlay tiles: longer side in pixels, contour width in pixels, voxels kept around the brain.
OVERLAY_TILE_PX = 256
OVERLAY_CONTOUR_PX = 2
OVERLAY_MARGIN_VOXELS = 3

#: Render images in the order the report shows them.
RENDER_ORDER = (
    "anterior", "posterior", "right", "left", "superior", "inferior",
    "cut_axial", "cut_coronal", "cut_sagittal",
)  # fmt: skip


#: Overlay file -> (the mask it contours, the mosaic's title).
_OVERLAY_MASKS = {
    "overlay_tumor.png": ("tumour", "tumour contour (abnormal slices framed)"),
    "overlay_brain.png": ("brain", "brain mask contour"),
}


def overlay_png(
    name: str,
    image_zyx: np.ndarray,
    affine: np.ndarray,
    brain_zyx: np.ndarray,
    tumour_zyx: np.ndarray,
    abnormal_slices: Sequence[int],
) -> bytes:
    """One overlay of :data:`OVERLAYS` (``name``) as PNG bytes.

    Only the slices with brain (or tumour: one outside the brain mask stays
    visible) are shown, each cropped to the bounding box of the brain and
    tumour over those slices (:data:`OVERLAY_MARGIN_VOXELS` around it), with
    a contour :data:`OVERLAY_CONTOUR_PX` pixels wide on
    :data:`OVERLAY_TILE_PX`-pixel tiles; a tile keeps its slice's 0-based
    index. Without brain or tumour anywhere every slice is shown whole.
    """
    abnormal = np.asarray(list(abnormal_slices), dtype=np.int64)
    brain = np.asarray(brain_zyx).astype(bool)
    tumour = np.asarray(tumour_zyx).astype(bool)
    region = brain | tumour
    which, title = _OVERLAY_MASKS[name]
    shown = region.any(axis=(1, 2))
    n_shown, n_slices = int(shown.sum()), int(shown.size)
    if 0 < n_shown < n_slices:  # say which slices are left out, and why
        title += f"; {n_shown} of {n_slices} slices, those with brain"
    rgb = overlay_mosaic(
        image_zyx, tumour if which == "tumour" else brain, affine, abnormal_slices=abnormal,
        title=title, slices=shown, crop_mask=region,
        crop_margin=OVERLAY_MARGIN_VOXELS, contour_px=OVERLAY_CONTOUR_PX, tile_px=OVERLAY_TILE_PX,
    )  # fmt: skip
    return encode_png(rgb)


def write_overlays(
    folder: Path,
    image_zyx: np.ndarray,
    affine: np.ndarray,
    brain_zyx: np.ndarray,
    tumour_zyx: np.ndarray,
    abnormal_slices: Sequence[int],
) -> list[str]:
    """Both overlays (:func:`overlay_png`) written into ``folder``; returns the file names."""
    for name in _OVERLAY_MASKS:
        data = overlay_png(name, image_zyx, affine, brain_zyx, tumour_zyx, abnormal_slices)
        (folder / name).write_bytes(data)
    return list(_OVERLAY_MASKS)


def write_surface_files(
    folder: Path,
    *,
    tumour: Mesh,
    simplified: Mesh,
    brain: Mesh,
    brain_viewer: Mesh,
    image_zyx: np.ndarray,
    affine: np.ndarray,
    tumour_mask: np.ndarray,
    brain_mask: np.ndarray,
    title: str,
    tumor_color_rgb: Sequence[float],
    brain_color_rgb: Sequence[float],
    brain_opacity: float,
) -> list[str]:
    """``brain_mesh.ply``, ``tumor_lps.vtk``, the STL files and ``viewer.html``; the names.

    ``tumor.stl`` and ``tumor_simplified.stl`` (binary, LPS millimetres with
    ``SPACE=LPS`` in the header: STL carries no coordinate system, and 3D
    Slicer, which reads that header, assumes LPS without it) hold the
    surface and the simplified surface. ``viewer.html``
    (:func:`tumor3d.storage.viewer.viewer_html`) shows ``image_zyx`` (the scan,
    ``affine`` to RAS) in three planes with ``tumour_mask`` and
    ``brain_mask`` over it, beside the simplified tumour and
    ``brain_viewer`` (the brain reduced for the browser) in 3-D; it is
    written without a tumour too (the slices still show what was missed).
    It loads the output folder's shared script
    (:func:`tumor3d.storage.viewer.write_viewer_assets`). Without a tumour no tumour
    surface file is written.
    """
    written = []
    if not brain.is_empty:
        (folder / "brain_mesh.ply").write_bytes(encode_ply(brain))
        written.append("brain_mesh.ply")
    html = viewer_html(
        image_zyx, affine, tumour_mask, brain_zyx=brain_mask,
        tumour_mesh=None if tumour.is_empty else simplified,
        brain_mesh=None if brain_viewer.is_empty else brain_viewer, title=title,
        tumor_color_rgb=tumor_color_rgb, brain_color_rgb=brain_color_rgb,
        brain_opacity=brain_opacity,
    )  # fmt: skip
    (folder / "viewer.html").write_text(html, encoding="utf-8")
    written.append("viewer.html")
    if tumour.is_empty:
        return written
    (folder / "tumor_lps.vtk").write_bytes(encode_vtk_polydata(tumour, space="LPS"))
    (folder / "tumor.stl").write_bytes(encode_stl(tumour, space="LPS"))
    (folder / "tumor_simplified.stl").write_bytes(encode_stl(simplified, space="LPS"))
    return [*written, "tumor_lps.vtk", "tumor.stl", "tumor_simplified.stl"]


def _num(row: Mapping[str, Any], key: str) -> float | None:
    v = row.get(key)
    if v is None or isinstance(v, bool):
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if np.isfinite(f) else None


def method_words(metrics: Mapping[str, Any]) -> str:
    """The segmentation method that ran, and its model, in words ("" when not recorded).

    >>> method_words({"segment_method": "learned", "segment_model": "forest + U-Net mean"})
    'learned (forest + U-Net mean)'
    >>> method_words({"segment_method": "robust", "segment_model": ""})
    'robust'
    >>> method_words({"segment_method": "given"})
    'none (the segmentation was given)'
    """
    method = str(metrics.get("segment_method") or "")
    model = str(metrics.get("segment_model") or "")
    if method == "given":
        return "none (the segmentation was given)"
    return f"{method} ({model})" if method and model else method


def orientation_words(orientation: Mapping[str, Any]) -> str:
    """How the input was read, from ``provenance.json``'s ``input.orientation``.

    >>> orientation_words({"stored": "LAS", "read_as": "LPS"})
    'stored LAS, read as LPS'
    >>> orientation_words({"stored": "LPS", "read_as": "LPS"})
    'LPS, read as stored'
    >>> orientation_words({"stored": "LPS", "read_as": "LPS", "stated": False})
    'LPS, read as stored (assumed: the input does not state its orientation)'
    """
    stored, read = str(orientation.get("stored")), str(orientation.get("read_as"))
    words = f"{stored}, read as stored" if stored == read else f"stored {stored}, read as {read}"
    if orientation.get("stated") is False:
        words += " (assumed: the input does not state its orientation)"
    return words


def patient_report_data(
    metrics: Mapping[str, Any],
    *,
    stage_runs: Iterable[Mapping[str, Any]],
    abnormal_slices: Sequence[int],
    files: Iterable[str],
    provenance: Mapping[str, Any] | None = None,
    names: Mapping[str, str] | None = None,
) -> dict[str, Any]:
    """The input of :func:`tumor3d.storage.report_html.patient_report_html` for one patient.

    Parameters
    ----------
    metrics : mapping
        The patient's ``metrics.parquet`` row.
    stage_runs : iterable of mapping
        Per stage ``stage``, ``compute_seconds``, ``cached`` (``StageRun`` dumps).
    abnormal_slices : sequence of int
        0-based indices of the slices flagged abnormal
        (:func:`tumor3d.segmentation.methods.slices_flagged`).
    files : iterable of str
        Names of the files published beside the report (links are made only
        to these).
    provenance : mapping, optional
        The ``provenance.json`` record.
    names : mapping, optional
        Default file name -> its path relative to the report, for a layout
        that moves files (``--layout bids``, :func:`tumor3d.storage.bids.relayout`);
        ``files`` are then the default names.
    """
    present = set(files)
    where = dict(names or {})
    found = bool(metrics.get("tumour_found", True))
    vols = {
        key: _num(metrics, f"volume_{key}_mm3")
        for key in ("eq7", "voxel", "mesh", "mesh_simplified")
        if f"volume_{key}_mm3" in metrics
    }
    data: dict[str, Any] = {
        "patient_id": str(metrics["patient_id"]),
        # ok or check (tumor3d.segmentation.review); a metrics row from before the status: ok
        "status": str(metrics.get("status") or "ok"),
        "review_reasons": split_notes(metrics.get("review_reasons")),
        "tumour_found": found,
        "measured": str(metrics.get("measured") or ""),
        "method": method_words(metrics),
        "volumes_mm3": vols,
        "notes": split_notes(metrics.get("notes")),
        "n_slices": int(metrics.get("n_slices", 0)),
        "abnormal_slices": [int(k) for k in abnormal_slices],
    }
    orientation = ((provenance or {}).get("input") or {}).get("orientation")
    if isinstance(orientation, Mapping) and orientation.get("stored"):
        data["orientation"] = orientation_words(orientation)
    ce = _num(metrics, "volume_eq7_ce")
    lo, hi = _num(metrics, "volume_eq7_ci95_low_mm3"), _num(metrics, "volume_eq7_ci95_high_mm3")
    if found and ce is not None and lo is not None and hi is not None:
        data["eq7_precision"] = {"ce": ce, "ci95_low_mm3": lo, "ci95_high_mm3": hi}
    meas: dict[str, str] = {}
    if found:
        for key, label in (
            ("rano_longest_mm", "RANO-style longest in-plane diameter"),
            ("rano_perpendicular_mm", "RANO-style perpendicular diameter"),
        ):
            if _num(metrics, key) is not None:
                meas[label] = f"{_num(metrics, key):.1f} mm"
        if _num(metrics, "rano_product_mm2") is not None:
            # whole mm²: the product of two diameters given to 0.1 mm has no decimal to tell
            meas["RANO-style product"] = f"{_num(metrics, 'rano_product_mm2'):,.0f} mm²"
        if metrics.get("rano_slice_index") is not None:
            meas["RANO-style slice (0-based)"] = str(int(metrics["rano_slice_index"]))
        if meas and str(metrics.get("modality") or "") in ("flair", "t2"):
            # RANO's bidimensional product is defined on contrast-enhancing tumour (T1c)
            meas["RANO-style diameters of"] = (
                f"the {str(metrics['modality']).upper()} whole tumour, oedema included (RANO "
                "measures contrast-enhancing tumour on T1c)"
            )
        if _num(metrics, "max_diameter_3d_mm") is not None:
            meas["largest 3-D diameter of the surface"] = (
                f"{_num(metrics, 'max_diameter_3d_mm'):.1f} mm"
            )
    data["measurements"] = meas
    counts = {}
    for key, label in (
        ("n_tumor_slices", "Slices with segmented tumour"),
        ("n_eq7_slices", "Slices summed by Eq. 7"),
    ):
        if metrics.get(key) is not None:
            counts[label] = int(metrics[key])
    if metrics.get("eq7_slice_rule"):
        counts["Eq. 7 slice rule"] = str(metrics["eq7_slice_rule"])
    data["slice_counts"] = counts
    for key in ("slab_height_mm", "slice_thickness_mm", "slice_gap_mm"):
        if _num(metrics, key) is not None:
            data[key] = _num(metrics, key)
    if metrics.get("faces_mc") is not None:
        data["faces_before"] = int(metrics["faces_mc"])
    if metrics.get("faces_simplified") is not None:
        data["faces_after"] = int(metrics["faces_simplified"])
    runs = list(stage_runs)
    data["stage_seconds"] = {str(r["stage"]): float(r["compute_seconds"]) for r in runs}
    data["stage_cached"] = {str(r["stage"]): bool(r["cached"]) for r in runs}
    data["renders"] = {
        name: where.get(f"render_{name}.png", f"render_{name}.png")
        for name in RENDER_ORDER
        if f"render_{name}.png" in present
    }
    if "render_turntable.gif" in present:
        data["turntable"] = where.get("render_turntable.gif", "render_turntable.gif")
    data["overlays"] = {
        cap: where.get(name, name) for name, cap in OVERLAYS.items() if name in present
    }
    if "viewer.html" in present:
        data["viewer"] = where.get("viewer.html", "viewer.html")
    if provenance is not None:
        data["provenance"] = dict(provenance)
    return data


def write_report(folder: Path, data: Mapping[str, Any]) -> str:
    """``report.html`` from :func:`patient_report_data`; returns its name."""
    (folder / "report.html").write_text(patient_report_html(data), encoding="utf-8")
    return "report.html"
