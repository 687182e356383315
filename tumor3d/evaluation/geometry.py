"""The interpolation (Table 4) and simplification (Figure 10) evaluations, registered.

Both are optional evaluations of ``tumor3d evaluate`` (``--evaluation
interpolation``, ``--evaluation simplification``): they cost more than the
default ``segmentation`` evaluation and measure the geometry stages on each
case rather than the segmentation.

``interpolation``
    Interpolation error apart from segmentation error: on the case's
    *reference*. A thin reference (slice step <= 1.5 mm along the acquired
    slice direction) gets both protocols of
    :mod:`tumor3d.evaluation.interpolation`: the paper's Table 4 (thick
    slices of 2 thin slices every 5, each middle slice of a tumour triplet
    re-created from its neighbours, Eq. 10 error) and the k-th-slice
    protocol (keep every 5th slice, reconstruct the rest, 3-D Dice, HD95
    and volume error against the full reference). A thick (native)
    reference gets Table 4 on its own slices (``step 1``), the paper's
    literal protocol. Methods: ``SE`` (Algorithm 1), ``SO``, ``LG`` and the
    pipeline's default (:class:`tumor3d.config.InterpolateConfig`'s method and
    parts: ``SO-EDT parts``).
``simplification``
    The published marching-cubes surface simplified by the paper's
    curvature method, Lindstrom-Turk and QSlim (fast-simplification) at
    P = 40, 60 and 80 %: symmetric Hausdorff distance of Eq. 11 (vertex
    sets, mm), the point-to-surface Hausdorff and mean distance (Metro) and
    the volume change.

Columns are prefixed ``interp_`` and ``simp_``; the per-triplet Table 4
rows go to ``evaluation_slices.parquet`` (``slice_index`` = the middle
slice).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from tumor3d.config import InterpolateConfig
from tumor3d.evaluation.grids import voxel_sizes_mm
from tumor3d.evaluation.interpolation.methods import METHODS
from tumor3d.evaluation.registry import EvaluationCase, EvaluationRows, register_evaluation

__all__ = [
    "INTERPOLATION_METHODS",
    "SIMPLIFICATION_METHODS",
    "SIMPLIFICATION_PERCENTS",
    "evaluate_interpolation",
    "evaluate_simplification",
]


def _default_interpolation() -> str:
    """The label of the pipeline's default interpolation (its method and parts).

    >>> _default_interpolation()
    'SO-EDT parts'
    """
    default = InterpolateConfig()
    wanted = {"method": default.method, "parts": default.parts}
    return next(label for label, kwargs in METHODS.items() if kwargs == wanted)


#: Interpolation methods compared (labels of :data:`tumor3d.evaluation.interpolation.METHODS`):
#: the paper's three and the pipeline's default.
INTERPOLATION_METHODS: tuple[str, ...] = ("SE", "SO", "LG", _default_interpolation())
#: Simplification methods compared (:func:`tumor3d.simplify.simplify_mesh`).
SIMPLIFICATION_METHODS: tuple[str, ...] = ("curvature", "memoryless", "qem")
#: Reductions P (% of faces removed), as the paper's Figure 9.
SIMPLIFICATION_PERCENTS: tuple[float, ...] = (40.0, 60.0, 80.0)
#: A reference whose slice step is at most this (mm) is thin (the k-th-slice protocol).
THIN_STEP_MM = 1.5


def _key(method: str) -> str:
    """A column-safe method label: ``"SE-EDT parts"`` -> ``"se_edt_parts"``."""
    return method.lower().replace("-", "_").replace(" ", "_")


def _slice_axis_of(affine: np.ndarray, direction: np.ndarray) -> int:
    """The voxel axis of ``affine`` most parallel to the world ``direction``."""
    cols = np.asarray(affine, dtype=float)[:3, :3]
    cos = np.abs(cols.T @ direction) / np.maximum(np.linalg.norm(cols, axis=0), 1e-12)
    return int(np.argmax(cos))


def evaluate_interpolation_summary(rows: list[dict[str, Any]]) -> str:
    """Mean Table 4 error and k-th-slice Dice per method, over the cases that have them."""
    lines = [
        "| method | Table 4 epsilon mean (%) | cases | k = 5 3-D Dice | k = 5 volume error (%) |",
        "|---|---|---|---|---|",
    ]
    for m in INTERPOLATION_METHODS:
        k = _key(m)
        eps = [r.get(f"interp_{k}_eps_percent") for r in rows]
        eps = [float(v) for v in eps if v is not None and v == v]
        dsc = [r.get(f"interp_{k}_k5_dice") for r in rows]
        dsc = [float(v) for v in dsc if v is not None and v == v]
        vol = [r.get(f"interp_{k}_k5_volume_error_percent") for r in rows]
        vol = [float(v) for v in vol if v is not None and v == v]

        def f(v: list[float], fmt: str) -> str:
            return fmt.format(np.mean(v)) if v else "-"

        lines.append(
            f"| {m} | {f(eps, '{:.1f}')} | {len(eps)} | {f(dsc, '{:.3f}')} | {f(vol, '{:+.1f}')} |"
        )
    return "\n".join(lines)


@register_evaluation(
    "interpolation",
    description="Table 4: interpolation error on the reference (Eq. 10 on tumour triplets; "
    f"k = 5 slice reconstruction Dice, HD95, volume error), {' / '.join(INTERPOLATION_METHODS)} "
    "(the last the pipeline's default)",
    summarize=evaluate_interpolation_summary,
    default=False,
)
def evaluate_interpolation(case: EvaluationCase) -> EvaluationRows:
    """Interpolation error of each method on the case's reference (see the module docstring)."""
    from tumor3d.evaluation.interpolation import kth_slice_rows, table4_rows

    out: dict[str, Any] = {}
    if case.reference is None or not np.any(case.reference):
        out["interp_protocol"] = "none (no reference tumour)"
        return EvaluationRows(patient=out)
    acq = np.asarray(case.acquired_affine, dtype=float)
    direction = acq[:3, case.slice_axis] / np.linalg.norm(acq[:3, case.slice_axis])
    ref_aff = np.asarray(case.reference_affine, dtype=float)
    axis = _slice_axis_of(ref_aff, direction)
    sizes = voxel_sizes_mm(ref_aff)
    inplane = [sizes[a] for a in range(3) if a != axis]
    label = np.moveaxis(np.asarray(case.reference, dtype=bool), axis, 0)
    thin = sizes[axis] <= THIN_STEP_MM
    if thin:  # the paper's geometry emulated: 2 thin slices every 5
        t4 = table4_rows(label, case=case.patient_id, step_slices=5, thickness_slices=2.0,
                         pixel_spacing_mm=inplane, methods=INTERPOLATION_METHODS,
                         include_itk=False)  # fmt: skip
        kth = kth_slice_rows(
            label, case=case.patient_id, spacing_mm=(sizes[axis], *inplane), steps=(5,),
            methods=INTERPOLATION_METHODS, include_itk=False,
        )  # fmt: skip
        for r in kth:
            k = _key(r["method"])
            out[f"interp_{k}_k5_dice"] = float(r["dice"])
            out[f"interp_{k}_k5_hd95_mm"] = float(r["hd95_mm"])
            out[f"interp_{k}_k5_volume_error_percent"] = float(r["volume_error_percent"])
        out["interp_protocol"] = "thin reference: Table 4 (2 mm every 5 mm) and k = 5"
    else:  # the acquired slices themselves: the paper's literal protocol
        t4 = table4_rows(label, case=case.patient_id, step_slices=1, thickness_slices=1.0,
                         pixel_spacing_mm=inplane, methods=INTERPOLATION_METHODS,
                         include_itk=False)  # fmt: skip
        out["interp_protocol"] = "thick reference: Table 4 on its own slices"
    slices = []
    for m in INTERPOLATION_METHODS:
        eps = [r["epsilon_percent"] for r in t4 if r["method"] == m]
        out[f"interp_{_key(m)}_eps_percent"] = float(np.mean(eps)) if eps else float("nan")
    out["interp_table4_triplets"] = len({r["slices"] for r in t4})
    for r in t4:
        slices.append({
            "slice_index": int(round(r["z_thin"])), "interp_method": r["method"],
            "interp_triplet": r["slices"], "interp_area_px": int(r["area_px"]),
            "interp_eps_percent": float(r["epsilon_percent"]),
        })  # fmt: skip
    return EvaluationRows(patient=out, slices=slices)


def evaluate_simplification_summary(rows: list[dict[str, Any]]) -> str:
    """Mean symmetric Hausdorff of Eq. 11 (vertex sets, mm) per method and P."""
    head = " | ".join(f"P = {p:g} %" for p in SIMPLIFICATION_PERCENTS)
    lines = [f"| method | {head} | cases |", "|---" * (len(SIMPLIFICATION_PERCENTS) + 2) + "|"]
    for m in SIMPLIFICATION_METHODS:
        cells, n = [], 0
        for p in SIMPLIFICATION_PERCENTS:
            v = [r.get(f"simp_{m}_p{p:g}_eq11_mm") for r in rows]
            v = [float(x) for x in v if x is not None and x == x]
            n = max(n, len(v))
            cells.append(f"{np.mean(v):.2f} mm" if v else "-")
        lines.append(f"| {m} | {' | '.join(cells)} | {n} |")
    return "\n".join(lines)


@register_evaluation(
    "simplification",
    description="Figure 10: the published surface simplified by curvature / Lindstrom-Turk / "
    "QSlim at P = 40, 60, 80 %: symmetric Hausdorff (Eq. 11; point to surface), mean "
    "distance, volume change",
    summarize=evaluate_simplification_summary,
    default=False,
)
def evaluate_simplification(case: EvaluationCase) -> EvaluationRows:
    """Each simplifier on the case's published marching-cubes surface (``tumor.ply``)."""
    from tumor3d.evaluation.simplification import simplification_rows

    mesh = case.extras.get("mesh_tumor")
    if mesh is None or getattr(mesh, "n_faces", 0) < 100:
        return EvaluationRows(patient={"simp_faces_in": 0})
    rows = simplification_rows(
        mesh, case=case.patient_id, methods=SIMPLIFICATION_METHODS,
        reduction_percents=SIMPLIFICATION_PERCENTS, n_samples=5000,
    )  # fmt: skip
    out: dict[str, Any] = {"simp_faces_in": int(mesh.n_faces)}
    for r in rows:
        k = f"simp_{r['method']}_p{float(r['reduction_percent']):g}"
        out[f"{k}_eq11_mm"] = float(r["shd_vertex_mm"])  # vertex to vertex, the paper's
        out[f"{k}_hausdorff_mm"] = float(r["hausdorff_mm"])  # point to surface (Metro)
        out[f"{k}_mean_distance_mm"] = float(r["mean_distance_mm"])
        out[f"{k}_volume_change_percent"] = float(r["volume_change_percent"])
    return EvaluationRows(patient=out)
