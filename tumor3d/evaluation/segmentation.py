"""The built-in evaluation: slices, pixels, 3-D overlap, surfaces and volumes.

For one patient against its reference (:class:`EvaluationCase`):

* Table 2 of the paper: confusion counts of abnormal-slice recognition, a
  slice being truly abnormal iff the reference (on the acquired slices) has
  tumour on it; for the published segmentation (``tp``... = slice has tumour
  in ``tumor_mask_slices``) and for the detector alone (``det_tp``...);
* Table 3: tumour pixels on the acquired slices, ``N_p`` and ``N_g``, and
  Eq. 9 ``|N_p - N_g| / N_g x 100``;
* Dice and Jaccard per truly abnormal slice, their mean, and pooled over all
  slices;
* 3-D: Dice/Jaccard of the interpolated mask sampled on the reference's
  grid, and the 95th-percentile and maximum symmetric surface distance in mm
  (:mod:`tumor3d.evaluation.metrics`) between the boundary voxels on that
  grid (``hd95_mm``, ``hd_max_mm``); and between the published
  marching-cubes surface (``tumor.ply``) and the reference's own
  marching-cubes surface (:func:`tumor3d.geometry.surface.extract_surface`), vertex
  to nearest vertex (``hd95_surface_mm``, ``hd_max_surface_mm``);
* volumes: each method of ``metrics.parquet`` against the reference volume
  (reference voxels x voxel volume), signed % error.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from tumor3d.evaluation import metrics as m
from tumor3d.evaluation.grids import voxel_sizes_mm
from tumor3d.evaluation.registry import (
    EvaluationCase,
    EvaluationRows,
    ReportColumn,
    ReportColumns,
    register_evaluation,
)

__all__ = ["COLUMNS", "VOLUME_COLUMNS", "evaluate_segmentation"]

#: metrics.parquet volume columns compared with the reference volume.
VOLUME_COLUMNS = ("volume_eq7_mm3", "volume_voxel_mm3", "volume_mesh_mm3")


_DICE_KEYS = ("dice_slices_mean", "dice_pooled", "dice_3d")
#: The columns the report (its table per case and summary per group) and the console
#: show of this evaluation's rows.
COLUMNS = ReportColumns(
    title="Overlap and surface distance",
    intro="Per configuration: mean Dice over the reference's tumour slices / pooled "
    "Dice on the acquired slices / 3-D Dice on the reference grid; HD95 / max HD "
    "in mm between boundary voxels on the reference grid, and between the "
    "vertices of the published marching-cubes surface and of the reference's "
    "marching-cubes surface (mesh).",
    table=(
        ReportColumn("Dice slice / pooled / 3-D", _DICE_KEYS, "{:.3f}"),
        ReportColumn("HD95 / HD (mm)", ("hd95_mm", "hd_max_mm"), "{:.1f}"),
        ReportColumn("mesh HD95 / HD (mm)", ("hd95_surface_mm", "hd_max_surface_mm"), "{:.1f}"),
    ),
    # "ref-slice Dice" averages the reference's tumour slices only, blind to slices
    # segmented where the reference has none (a user audit: 0.926 beside a +118 % volume);
    # the pooled Dice of every acquired slice counts them
    summary=(
        ReportColumn("ref-slice Dice", ("dice_slices_mean",), "{:.3f}"),
        ReportColumn("pooled Dice", ("dice_pooled",), "{:.3f}"),
        ReportColumn("3-D Dice", ("dice_3d",), "{:.3f}"),
        ReportColumn("HD95 (mm)", ("hd95_mm",), "{:.1f}"),
        ReportColumn("Eq. 9 (%)", ("eq9_percent",), "{:.1f}"),
        ReportColumn("Eq. 7 err. (%)", ("volume_eq7_error_percent",), "{:+.1f}"),
        ReportColumn("mesh err. (%)", ("volume_mesh_error_percent",), "{:+.1f}"),
    ),
    # HD95 in REPORT.md only: an 80-column terminal holds the patient's id whole
    console=(
        ReportColumn("Dice ref slices", ("dice_slices_mean",), "{:.3f}"),
        ReportColumn("Dice pooled", ("dice_pooled",), "{:.3f}"),
        ReportColumn("3-D Dice", ("dice_3d",), "{:.3f}"),
        ReportColumn("Eq. 7 err", ("volume_eq7_error_percent",), "{:+.1f} %"),
    ),
)


@register_evaluation(
    "segmentation",
    description="slice recognition (Table 2), pixel counts (Table 3), Dice/Jaccard, "
    "3-D Dice, HD95/HD max and volume errors against the reference",
    columns=COLUMNS,
)
def evaluate_segmentation(case: EvaluationCase) -> EvaluationRows:
    """Compare one patient's segmentation, 3-D mask and volumes with its reference.

    Parameters
    ----------
    case : EvaluationCase

    Returns
    -------
    EvaluationRows
        ``patient``: ``tp, fp, tn, fn``, ``det_tp, det_fp, det_tn, det_fn``,
        ``n_p, n_g, eq9_percent``, ``dice_slices_mean``, ``jaccard_slices_mean``,
        ``dice_pooled``, ``jaccard_pooled``, ``n_ref_slices``, ``dice_3d``,
        ``jaccard_3d``, ``hd95_mm``, ``hd_max_mm``, ``hd95_surface_mm``,
        ``hd_max_surface_mm``, ``ref_volume_mm3``, and per
        volume method ``<method>_error_percent`` (signed). ``slices``: per
        acquired slice ``slice_index`` (in the published masks' order: the input
        file's), ``n_p``, ``n_g``, ``truly_abnormal``,
        ``pred_abnormal``, ``detector_abnormal``, ``dice``, ``jaccard``,
        ``eq9_percent``. Everything needing a reference is ``nan`` without one.
    """
    if not isinstance(case, EvaluationCase):
        raise TypeError(f"case must be an EvaluationCase, got {type(case).__name__}")
    nan = float("nan")
    ax = case.slice_axis
    pred = np.moveaxis(case.pred_slices.astype(bool), ax, 0)
    n_slices = pred.shape[0]
    n_p_slice = pred.reshape(n_slices, -1).sum(axis=1)
    det = case.detector_abnormal
    if det is not None and det.shape != (n_slices,):
        det = None  # a detector table that does not match the slices is not used
    row: dict[str, Any] = {"reference_kind": case.reference_kind, "n_slices": int(n_slices)}
    slices: list[dict[str, Any]] = []
    if case.ref_slices is None:
        for i in range(n_slices):
            slices.append(
                {"slice_index": i, "n_p": int(n_p_slice[i]), "n_g": None,
                 "truly_abnormal": None, "pred_abnormal": bool(n_p_slice[i] > 0),
                 "detector_abnormal": None if det is None else bool(det[i]),
                 "dice": nan, "jaccard": nan, "eq9_percent": nan}
            )  # fmt: skip
        row.update(n_p=int(n_p_slice.sum()))
        return EvaluationRows(patient=row, slices=slices)

    ref = np.moveaxis(case.ref_slices.astype(bool), ax, 0)
    n_g_slice = ref.reshape(n_slices, -1).sum(axis=1)
    conf = m.slice_confusion(n_p_slice > 0, n_g_slice)
    row.update(tp=conf.tp, fp=conf.fp, tn=conf.tn, fn=conf.fn)
    if det is not None:
        dconf = m.slice_confusion(det.astype(bool), n_g_slice)
        row.update(det_tp=dconf.tp, det_fp=dconf.fp, det_tn=dconf.tn, det_fn=dconf.fn)
    dices, jaccards = [], []
    for i in range(n_slices):
        truly = bool(n_g_slice[i] > 0)
        d = m.dice(pred[i], ref[i]) if truly else nan
        j = m.jaccard(pred[i], ref[i]) if truly else nan
        if truly:
            dices.append(d)
            jaccards.append(j)
        slices.append(
            {"slice_index": i, "n_p": int(n_p_slice[i]), "n_g": int(n_g_slice[i]),
             "truly_abnormal": truly, "pred_abnormal": bool(n_p_slice[i] > 0),
             "detector_abnormal": None if det is None else bool(det[i]),
             "dice": d, "jaccard": j,
             "eq9_percent": m.relative_error_percent(int(n_p_slice[i]), int(n_g_slice[i]))}
        )  # fmt: skip
    n_p, n_g = int(n_p_slice.sum()), int(n_g_slice.sum())
    row.update(
        n_p=n_p,
        n_g=n_g,
        eq9_percent=m.relative_error_percent(n_p, n_g),
        n_ref_slices=len(dices),
        dice_slices_mean=float(np.mean(dices)) if dices else nan,
        jaccard_slices_mean=float(np.mean(jaccards)) if jaccards else nan,
        dice_pooled=m.dice(pred, ref),
        jaccard_pooled=m.jaccard(pred, ref),
    )

    if case.reference is not None and case.pred_on_reference is not None:
        reference = case.reference.astype(bool)
        on_ref = case.pred_on_reference.astype(bool)
        spacing = voxel_sizes_mm(case.reference_affine)
        dist = m.surface_distances_mm(on_ref, reference, spacing)
        hd95, hdmax = m.hausdorff_mm(dist, 95.0)
        voxel_mm3 = float(abs(np.linalg.det(case.reference_affine[:3, :3])))
        ref_volume = float(reference.sum()) * voxel_mm3
        hd95_s = hdmax_s = nan
        mesh = case.extras.get("mesh_tumor")
        if mesh is not None and len(mesh.vertices) and reference.any():
            from tumor3d.geometry.surface import extract_surface

            # extract_surface takes (z, y, x) with an affine of (x, y, z): the
            # reference's own (i0, i1, i2) order reversed, with its affine unchanged
            ref_mesh = extract_surface(reference.transpose(2, 1, 0), case.reference_affine)
            hd95_s, hdmax_s = m.hausdorff_mm(
                m.point_set_distances_mm(mesh.vertices, ref_mesh.vertices), 95.0
            )
        row.update(
            hd95_surface_mm=hd95_s,
            hd_max_surface_mm=hdmax_s,
            dice_3d=m.dice(on_ref, reference),
            jaccard_3d=m.jaccard(on_ref, reference),
            hd95_mm=hd95,
            hd_max_mm=hdmax,
            ref_volume_mm3=ref_volume,
        )
        for col in VOLUME_COLUMNS:
            value = case.metrics.get(col)
            row[col.replace("_mm3", "_error_percent")] = (
                nan if value is None or not np.isfinite(value)
                else m.signed_percent_error(float(value), ref_volume)
            )  # fmt: skip
    return EvaluationRows(patient=row, slices=slices)
