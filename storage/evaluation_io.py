"""File side of the evaluation: emulated inputs, references, published outputs.

* :func:`prepare_case` checks one manifest row for evaluation (reference
  readable, in the image's world space, holding the requested labels;
  emulation possible) and, for an emulated row, writes the thick-slice image
  ``<work_dir>/<patient_id>/<patient_id>_<modality>.nii.gz`` with a BIDS
  sidecar (``SliceThickness``, ``SpacingBetweenSlices``) that the NIfTI
  reader honours, and, for a row with a ``brain_mask``, the mask emulated
  the same way (``<patient_id>_brain_mask.nii.gz``: brain where the mean of
  the thin mask, brain = values > 0.5, over the slab is >= 0.5, on the
  emulated image's grid), and returns the row the pipeline runs on;
* :func:`load_case` reads a patient's published outputs
  (``tumor_mask_slices.nii.gz``, ``tumor_mask.nii.gz``, ``slices.parquet``,
  ``metrics.parquet``, ``tumor.ply``, ``tumor_simplified.ply``) and its
  reference, puts them on comparable grids, and builds the pure
  :class:`tumor3d.evaluation.EvaluationCase`;

The manifests' rows gathered, one configuration's run turned into the rows of
``evaluation.parquet`` and their writing: :mod:`tumor3d.storage.evaluation_tables`.

Every problem of a row is an :class:`~tumor3d.errors.InputError` naming the
row's patient id (and the file).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from tumor3d.errors import InputError
from tumor3d.evaluation import EvaluationCase
from tumor3d.evaluation.emulate import emulate_thick_labels, emulate_thick_slices
from tumor3d.evaluation.grids import grids_overlap, resample_nearest, same_grid
from tumor3d.imaging.brain_mask import binarize_brain_mask, check_same_grid
from tumor3d.storage import nifti
from tumor3d.storage.atomic import atomic_write_bytes
from tumor3d.storage.brain_mask import read_brain_mask_volume
from tumor3d.storage.formats import decode_parquet, decode_ply
from tumor3d.storage.manifest import ManifestRow
from tumor3d.storage.readers import choose_slice_axis

__all__ = [
    "PreparedCase",
    "acquired_reference",
    "detector_flags",
    "load_case",
    "prepare_case",
    "reference_mask",
]


@dataclass(frozen=True)
class PreparedCase:
    """A manifest row ready for evaluation.

    Parameters
    ----------
    source : ManifestRow
        The row as written in the manifest.
    run_row : ManifestRow
        The row the pipeline runs on (its image is the emulated one, if any).
    reference_kind : str
        ``expert``, ``semiautomatic``, ``algorithmic``, ``truth``, ``tumor_free`` or
        ``unspecified``.
    acquisition : str
        ``"native"`` or e.g. ``"emulated 2 mm every 5 mm"``.
    emulation : dict or None
        ``step_mm``, ``thickness_mm``, ``gap_mm``, ``axis``, ``thin_indices``
        (list of lists) for an emulated row.
    """

    source: ManifestRow
    run_row: ManifestRow
    reference_kind: str
    acquisition: str
    emulation: dict[str, Any] | None = None


def _squeeze3(array: np.ndarray, where: str) -> np.ndarray:
    if array.ndim == 4 and array.shape[3] == 1:
        array = array[..., 0]
    if array.ndim != 3:
        raise InputError(f"expected a 3-D volume, got shape {array.shape}", where)
    return array


#: A reference with more distinct values and no labels named is an image, not a label map
#: (BraTS has 4 labels; a map of many structures names its tumour's, ``reference_labels``).
MAX_REFERENCE_LABELS = 32


def reference_mask(row: ManifestRow) -> tuple[np.ndarray, np.ndarray]:
    """Read a row's reference as a boolean tumour mask ``(mask, affine)``.

    The tumour is the voxels whose (rounded) label is in
    ``row.reference_labels``, or every label > 0 when none are given.

    Raises
    ------
    InputError
        Unreadable file, non-integer labels, more than :data:`MAX_REFERENCE_LABELS`
        distinct values where no labels are named (an image given as the reference;
        a label map of many structures names its tumour's labels), or none of the
        requested labels present.
    """
    if row.reference is None:
        raise InputError(f"patient {row.patient_id}: no reference in the manifest")
    where = str(row.reference)
    labels, affine = nifti.read_nifti(row.reference)
    labels = _squeeze3(np.asarray(labels), where)
    if labels.dtype.kind in "biu":  # stored as integers: labels as they are (no copy)
        rounded = labels
    else:  # stored as floats (or scaled): integers within 1e-3, finite
        if not np.all(np.isfinite(labels)):
            raise InputError(
                f"patient {row.patient_id}: the reference has non-finite values", where
            )
        rounded = np.rint(labels)
        if np.any(np.abs(labels - rounded) > 1e-3):
            raise InputError(
                f"patient {row.patient_id}: the reference labels are not integers", where
            )
        rounded = rounded.astype(np.int64)
    if row.reference_labels is None:
        values = np.unique(rounded)
        if values.size > MAX_REFERENCE_LABELS:  # gray levels, not labels: all "tumour"
            raise InputError(
                f"patient {row.patient_id}: the reference holds {values.size} distinct "
                f"values ({values[0]}-{values[-1]}): an image, not a label map (at most "
                f"{MAX_REFERENCE_LABELS} labels)",
                where,
            )
        mask = rounded > 0
        if not mask.any() and row.reference_kind != "tumor_free":
            raise InputError(
                f"patient {row.patient_id}: the reference has no label > 0 (a patient "
                "without tumour: give the row reference_kind tumor_free and no reference)",
                where,
            )
    else:
        mask = np.isin(rounded, row.reference_labels)
        if not mask.any():
            present = sorted(int(v) for v in np.unique(rounded) if v > 0)
            raise InputError(
                f"patient {row.patient_id}: the reference has none of the requested labels "
                f"{','.join(map(str, row.reference_labels))} (present: "
                f"{','.join(map(str, present)) or 'none'})",
                where,
            )
    return mask, affine


def _read_image(row: ManifestRow) -> tuple[np.ndarray, np.ndarray]:
    name = row.image.name.lower()
    if not (row.image.is_file() and (name.endswith(".nii") or name.endswith(".nii.gz"))):
        raise InputError(
            f"patient {row.patient_id}: emulation needs a NIfTI image file", str(row.image)
        )
    image, affine = nifti.read_nifti(row.image)
    return _squeeze3(np.asarray(image), str(row.image)), affine


def _image_grid(row: ManifestRow) -> tuple[tuple[int, int, int], np.ndarray]:
    """Shape and affine of a row's image (NIfTI header only; other inputs via the reader)."""
    name = row.image.name.lower()
    if row.image.is_file() and (name.endswith(".nii") or name.endswith(".nii.gz")):
        import nibabel as nib

        img = nib.load(str(row.image))
        shape = tuple(int(s) for s in img.shape[:3])
        return shape, nifti.placed_affine(img)  # type: ignore[return-value]
    from tumor3d.storage.readers import read_scan

    scan = read_scan(row.image, modality=row.modality, patient_id=row.patient_id)
    grid = scan.source_grid
    return grid.shape, np.asarray(grid.affine)


def prepare_case(row: ManifestRow, work_dir: str | Path) -> PreparedCase:
    """Check a row for evaluation and write its emulated image if it asks for one.

    Parameters
    ----------
    row : ManifestRow
    work_dir : path
        Emulated images go to ``<work_dir>/<patient_id>/``.

    Returns
    -------
    PreparedCase

    Raises
    ------
    InputError
        Naming the patient: the reference is unreadable, does not overlap the
        image in world space or holds none of the requested labels; emulation
        on a non-NIfTI image, on slices already thicker than the step, or
        combined with thickness/gap overrides.
    """
    kind = row.reference_kind or "unspecified"
    shape, aff = _image_grid(row)
    if row.reference is not None:
        ref_mask, ref_aff = reference_mask(row)
        if not grids_overlap(shape, aff, ref_mask.shape, ref_aff):
            raise InputError(
                f"patient {row.patient_id}: the reference does not overlap the image "
                f"{row.image.name} in world space",
                str(row.reference),
            )
    if row.emulate_step_mm is None:
        step = float(np.linalg.norm(aff[:3, choose_slice_axis(aff)]))
        return PreparedCase(row, row, kind, f"native, {step:.3g} mm slice step")
    if row.slice_thickness_mm is not None or row.slice_gap_mm is not None:
        raise InputError(
            f"patient {row.patient_id}: slice_thickness_mm/slice_gap_mm cannot be combined "
            "with emulation (the emulated image states its own)"
        )
    image, affine = _read_image(row)
    axis = choose_slice_axis(affine)
    thin_step = float(np.linalg.norm(affine[:3, axis]))
    thickness = row.emulate_thickness_mm if row.emulate_thickness_mm is not None else thin_step
    try:
        thick = emulate_thick_slices(
            image, affine, axis=axis, step_mm=row.emulate_step_mm, thickness_mm=thickness
        )
    except InputError as exc:
        raise InputError(f"patient {row.patient_id}: {exc.problem}", str(row.image)) from None
    folder = Path(work_dir) / row.patient_id
    folder.mkdir(parents=True, exist_ok=True)
    out = folder / f"{row.patient_id}_{row.modality}.nii.gz"
    atomic_write_bytes(out, nifti.encode_nifti(thick.volume, thick.affine, dtype="float32"))
    plan = thick.thin_indices
    first, k = int(plan[0, 0]), int(plan[1, 0] - plan[0, 0])
    last = first + plan.shape[1] - 1
    sidecar = {
        "SliceThickness": thick.thickness_mm,
        "SpacingBetweenSlices": thick.step_mm,
        "tumor3dEmulatedFrom": row.image.name,
        "tumor3dThinSlices": f"thick slice j = mean of thin slices {first}+{k}j .. {last}+{k}j "
        f"along voxel axis {axis}",
    }
    atomic_write_bytes(
        folder / f"{row.patient_id}_{row.modality}.json",
        (json.dumps(sidecar, indent=2) + "\n").encode(),
    )
    mask_out = None
    if row.brain_mask is not None:
        mask_out = folder / f"{row.patient_id}_brain_mask.nii.gz"
        brain = _thin_brain_mask(row, image, affine)
        lab = emulate_thick_labels(
            brain, affine, axis=axis, step_mm=row.emulate_step_mm, thickness_mm=thickness
        )
        atomic_write_bytes(mask_out, nifti.encode_nifti(lab.volume, lab.affine, dtype="uint8"))
        mask_out = mask_out.resolve()
    run_row = replace(
        row, image=out.resolve(), emulate_step_mm=None, emulate_thickness_mm=None,
        brain_mask=mask_out,
    )  # fmt: skip
    emulation = {
        "step_mm": thick.step_mm,
        "thickness_mm": thick.thickness_mm,
        "gap_mm": thick.gap_mm,
        "axis": axis,
        "thin_indices": thick.thin_indices.tolist(),
        "thin_shape": list(image.shape),
        "thin_affine": affine.tolist(),
    }
    label = f"emulated {thick.thickness_mm:g} mm every {thick.step_mm:g} mm"
    return PreparedCase(row, run_row, kind, label, emulation)


def _thin_brain_mask(row: ManifestRow, image: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """A row's brain mask (values > 0.5) checked against its thin image, in the file's order."""
    assert row.brain_mask is not None
    try:
        values, mask_affine = read_brain_mask_volume(row.brain_mask)
        check_same_grid(values.shape, mask_affine, image.shape, affine)
        return binarize_brain_mask(values, image)
    except InputError as exc:
        problem = exc.problem.removeprefix("brain mask: ")
        raise InputError(
            f"patient {row.patient_id}: brain mask: {problem}", exc.path or str(row.brain_mask)
        ) from None


def acquired_reference(
    prepared: PreparedCase, reference: tuple[np.ndarray, np.ndarray] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The reference on the slices the pipeline reads: ``(mask, affine)``, in file order.

    For an emulated row, the reference sampled (nearest) on the thin image's
    grid and emulated like the image (tumour where the mean over a thick
    slice's thin slices is >= 0.5), on the emulated image's grid; for a
    native row, the reference as read (the caller samples it on the image's
    grid). ``reference``, if given, is the row's :func:`reference_mask`
    already read.
    """
    row = prepared.source
    if row.reference is None:
        raise InputError(f"patient {row.patient_id}: no reference given", str(row.image))
    ref, ref_aff = reference if reference is not None else reference_mask(row)
    if prepared.emulation is None:
        return ref, ref_aff
    e = prepared.emulation
    thin_shape, thin_aff = tuple(e["thin_shape"]), np.asarray(e["thin_affine"])
    ref_thin = resample_nearest(ref, ref_aff, thin_shape, thin_aff)
    lab = emulate_thick_labels(
        ref_thin, thin_aff, axis=e["axis"], step_mm=e["step_mm"], thickness_mm=e["thickness_mm"]
    )
    return lab.volume, lab.affine


def detector_flags(slices: Any, n_slices: int) -> np.ndarray | None:
    """The detection's ``abnormal`` flag per slice of ``slices.parquet``, in the file's order.

    The published masks are in the input file's slice order; ``slice_index`` is the
    working order (reversed for a file that stores its slices the other way round), and
    ``file_slice_index`` the file's (absent in results published before it: the same
    order then). None without the columns, or for another number of slices.

    >>> import pandas as pd
    >>> top_down = pd.DataFrame({"slice_index": [0, 1, 2], "abnormal": [False, True, True],
    ...                          "file_slice_index": [2, 1, 0]})
    >>> detector_flags(top_down, 3).tolist()
    [True, True, False]
    >>> detector_flags(top_down.drop(columns="file_slice_index"), 3).tolist()
    [False, True, True]
    """
    if "abnormal" not in slices.columns or "slice_index" not in slices.columns:
        return None
    index = "file_slice_index" if "file_slice_index" in slices.columns else "slice_index"
    order = slices.sort_values(index)
    return order["abnormal"].to_numpy(dtype=bool) if len(order) == n_slices else None


def load_case(prepared: PreparedCase, output_dir: str | Path) -> EvaluationCase:
    """Read one patient's published outputs and its reference into an EvaluationCase.

    Grids: the per-slice reference is the reference sampled (nearest) on the
    thin image grid and emulated like the image, or, for a native row,
    sampled at the image's voxel centres; the 3-D comparison samples the
    interpolated mask at the full-resolution reference's voxel centres
    (nearest neighbour, :func:`tumor3d.evaluation.grids.resample_nearest`).
    A ``tumor_free`` row has an empty reference on the image grid.

    Parameters
    ----------
    prepared : PreparedCase
    output_dir : path
        The patient's published folder (``<out>/<patient_id>/``).
    """
    out = Path(output_dir)
    pid = prepared.source.patient_id
    pred_slices, acq_aff = nifti.read_nifti(out / "tumor_mask_slices.nii.gz")
    pred_slices = _squeeze3(np.asarray(pred_slices), str(out)) > 0
    pred_fine, fine_aff = nifti.read_nifti(out / "tumor_mask.nii.gz")
    pred_fine = _squeeze3(np.asarray(pred_fine), str(out)) > 0
    slices = decode_parquet((out / "slices.parquet").read_bytes())
    metrics = decode_parquet((out / "metrics.parquet").read_bytes()).iloc[0].to_dict()
    axis = choose_slice_axis(acq_aff)
    det = detector_flags(slices, pred_slices.shape[axis])

    reference = ref_aff = ref_slices = on_ref = None
    row = prepared.source
    if row.reference is not None:
        reference, ref_aff = reference_mask(row)
        ref_slices, slices_aff = acquired_reference(prepared, (reference, ref_aff))
        if prepared.emulation is not None and not same_grid(
            ref_slices.shape, slices_aff, pred_slices.shape, acq_aff
        ):
            raise InputError(f"patient {pid}: the emulated reference does not match the "
                             "emulated image's grid", str(out))  # fmt: skip
        if prepared.emulation is None:
            ref_slices = resample_nearest(reference, ref_aff, pred_slices.shape, acq_aff)
        on_ref = resample_nearest(pred_fine, fine_aff, reference.shape, ref_aff)
    elif prepared.reference_kind == "tumor_free":
        ref_slices = np.zeros_like(pred_slices)
        reference, ref_aff = np.zeros_like(pred_slices), acq_aff
        on_ref = resample_nearest(pred_fine, fine_aff, reference.shape, ref_aff)

    extras: dict[str, Any] = {"output_dir": str(out)}
    for name in ("tumor", "tumor_simplified"):
        ply = out / f"{name}.ply"
        if ply.is_file():
            try:
                extras[f"mesh_{name}"] = decode_ply(ply.read_bytes(), name=str(ply))
            except InputError:
                pass  # no usable mesh (e.g. no tumour found)
    return EvaluationCase(
        patient_id=pid,
        reference_kind=prepared.reference_kind,
        slice_axis=axis,
        acquired_affine=acq_aff,
        pred_slices=pred_slices,
        ref_slices=ref_slices,
        detector_abnormal=det,
        pred_fine=pred_fine,
        pred_fine_affine=fine_aff,
        reference=reference,
        reference_affine=ref_aff,
        pred_on_reference=on_ref,
        metrics=metrics,
        extras=extras,
    )


# --------------------------------------------------------------------------- cohort rows
