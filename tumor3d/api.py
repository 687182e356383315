"""The Python entry: :func:`reconstruct` one patient in this process, no Prefect, no server.

>>> import tumor3d
>>> r = tumor3d.reconstruct("flair.nii.gz", modality="flair")   # doctest: +SKIP
>>> r.status, r.volumes_ml["eq7"], r.eq7_ci95_ml                # doctest: +SKIP
('ok', 21.97, (21.0, 22.9))

The stages are the pipeline's (the same core functions, in the same order,
with the same configuration as ``tumor3d run``): preprocessing and brain
mask, abnormal-slice detection, segmentation, interpolation between slices,
marching cubes, simplification and the volumes with Eq. 7's predicted
precision; renders, overlays and files are left to the command line. Nothing
is cached or written.

The core stays pure: arrays (or a :class:`~tumor3d.imaging.scan.Scan`) go in. A path
is read, and an array with its affine is turned into a ``Scan``, by
:mod:`tumor3d.storage.readers`, imported only then.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tumor3d.config import PipelineConfig, as_config
from tumor3d.errors import InputError
from tumor3d.geometry.measures import clinical_measures
from tumor3d.geometry.mesh import Mesh
from tumor3d.imaging.affine import reverse_axes, slab_height_mm, slice_overlap_note
from tumor3d.imaging.identity import MODALITIES
from tumor3d.imaging.orientation import canonical_flips, canonical_orientation, slice_order_note
from tumor3d.imaging.scan import Scan
from tumor3d.metrics import measure_volumes
from tumor3d.segmentation.lesion import left_right_axis
from tumor3d.segmentation.review import brain_mask_run_notes, review_status, run_notes

__all__ = ["Reconstruction", "reconstruct", "reconstruct_scan", "segmentation_values"]

#: The volume estimators, as in ``metrics.parquet`` (``volume_<key>_mm3``).
VOLUME_KEYS = ("eq7", "voxel", "mesh", "mesh_simplified")


@dataclass(frozen=True, eq=False)  # arrays inside: == is identity, as numpy's results
class Reconstruction:
    """What :func:`reconstruct` returns.

    Arrays are in the pipeline's ``(z, y, x)`` order (``z`` the slice axis)
    with ``affine`` mapping ``(x, y, z, 1)`` to RAS mm, on ``scan``'s grid, in
    the working orientation (LPS for an axial stack:
    :func:`tumor3d.imaging.scan.canonical_orientation`); :meth:`on_input_grid`
    puts a mask back in the input's own voxel order.

    Attributes
    ----------
    patient_id, modality : str
    status : {"ok", "check"}
        ``check``: the tool's own checks doubt the result; ``review_reasons``
        say why (:mod:`tumor3d.segmentation.review`).
    review_reasons : tuple of str
    notes : tuple of str
        Every note of the run (the reasons included).
    method : str
        The segmentation method that ran (``auto`` resolved).
    measured : str
        What the mask, and so every volume, holds, in words.
    volumes_mm3, volumes_ml : dict of str to float
        ``eq7`` (slab sum, the paper's Eq. 7), ``voxel``, ``mesh`` and
        ``mesh_simplified``.
    eq7_ce : float
        Predicted coefficient of error of the Eq. 7 volume.
    eq7_ci95_mm3, eq7_ci95_ml : (float, float)
        Its 95 % interval.
    tumor_mask_slices : (z, y, x) ndarray of bool
        The segmentation on the acquired slices.
    brain_mask : (z, y, x) ndarray of bool
    affine : (4, 4) ndarray
        Of the acquired grid.
    tumor_mask : (Z, y, x) ndarray of bool
        The tumour after interpolation between slices, on ``fine_affine``.
    fine_affine : (4, 4) ndarray
    mesh, mesh_simplified : Mesh
        RAS mm; empty when no tumour was found.
    metrics : dict
        Every measurement (the measure stage's row: RANO diameters, counts...).
    tumor_probability : (z, y, x) ndarray of float32 or None
        The learned method's lesion probability per voxel (None for the other
        methods).
    """

    patient_id: str
    modality: str
    status: str
    review_reasons: tuple[str, ...]
    notes: tuple[str, ...]
    method: str
    measured: str
    volumes_mm3: dict[str, float]
    volumes_ml: dict[str, float]
    eq7_ce: float
    eq7_ci95_mm3: tuple[float, float]
    eq7_ci95_ml: tuple[float, float]
    tumor_mask_slices: np.ndarray = field(repr=False)
    brain_mask: np.ndarray = field(repr=False)
    affine: np.ndarray = field(repr=False)
    tumor_mask: np.ndarray = field(repr=False)
    fine_affine: np.ndarray = field(repr=False)
    mesh: Mesh = field(repr=False)
    mesh_simplified: Mesh = field(repr=False)
    metrics: dict[str, Any] = field(repr=False, default_factory=dict)
    scan: Scan | None = field(repr=False, default=None)
    tumor_probability: np.ndarray | None = field(repr=False, default=None)

    @property
    def needs_review(self) -> bool:
        """True when the status is ``check``."""
        return self.status != "ok"

    @property
    def tumour_found(self) -> bool:
        """Whether any tumour was segmented."""
        return bool(np.any(self.tumor_mask_slices))

    def on_input_grid(self, mask_zyx: np.ndarray) -> np.ndarray:
        """A ``(z, y, x)`` array of the acquired grid in the input's own voxel order."""
        if self.scan is None:
            raise InputError("no input grid recorded")
        mask = np.asarray(mask_zyx)
        grid = self.tumor_mask_slices.shape
        if mask.shape != grid:
            raise InputError(
                f"on_input_grid takes an array of the acquired grid (z, y, x) {grid}, not one "
                f"of shape {mask.shape} (the interpolated tumor_mask lies on fine_affine)"
            )
        return self.scan.source_grid.to_source(mask)


def _modality(modality: str | None, scan: Scan | None) -> str:
    if modality is None:
        if scan is not None:
            return scan.modality
        raise InputError(
            f"give modality= ({', '.join(MODALITIES)}): it decides the segmentation method, "
            "and is never assumed"
        )
    m = str(modality).strip().lower()
    if m not in MODALITIES:
        raise InputError(f"unknown modality {modality!r}: expected one of {', '.join(MODALITIES)}")
    return m


def segmentation_values(seg: Any) -> dict[str, Any]:
    """A segmentation's own review, as the segment-tumor stage's values hold it.

    ``needs_review``, ``review_reasons`` and ``quality_score`` read from the
    segmentation result, or from its ``review`` (an object with
    ``needs_review``, ``reasons`` and ``quality_score``, as
    :class:`tumor3d.learned.review.Review`); absent ones are left out (no doubt).

    >>> from types import SimpleNamespace as NS
    >>> segmentation_values(NS(review=NS(needs_review=True, reasons=("low",), quality_score=.3)))
    {'needs_review': True, 'review_reasons': ['low'], 'quality_score': 0.3}
    >>> segmentation_values(NS(method="robust"))
    {}
    """
    src = getattr(seg, "review", None) or seg
    out: dict[str, Any] = {}
    if getattr(src, "needs_review", None) is not None:
        out["needs_review"] = bool(src.needs_review)
    reasons = getattr(src, "review_reasons", None)
    reasons = getattr(src, "reasons", None) if reasons is None else reasons
    if reasons is not None:
        out["review_reasons"] = [str(r) for r in reasons]
    if getattr(src, "quality_score", None) is not None:
        out["quality_score"] = float(src.quality_score)
    return out


def reconstruct_scan(
    scan: Scan,
    *,
    config: PipelineConfig | Mapping[str, Any] | str | None = None,
    brain_mask: np.ndarray | None = None,
    segmentation: np.ndarray | None = None,
    segmentation_name: str | None = None,
    header_notes: Sequence[str] = (),
    models: Mapping[str, bytes] | None = None,
) -> Reconstruction:
    """Run the pipeline's stages on a :class:`~tumor3d.imaging.scan.Scan` (pure: arrays in and out).

    A scan in another orientation than the readers' working one (a Scan built by
    hand with an RAS affine, say) is first reversed into it
    (:func:`~tumor3d.imaging.scan.canonical_orientation`), as a file is, so that the
    learned method reads it as it was trained; the result's arrays are on the
    reversed scan (``Reconstruction.scan``), and its ``on_input_grid`` puts them back.

    Parameters
    ----------
    scan : Scan
    config : PipelineConfig, dict or YAML text, optional
        As ``tumor3d run --config`` (defaults when None).
    brain_mask : (z, y, x) ndarray, optional
        A brain mask on the scan's grid (brain = values > 0.5), used instead
        of skull removal.
    segmentation : (z, y, x) ndarray, optional
        A tumour mask on the scan's grid (tumour = values > 0.5), used instead
        of the segmentation (:mod:`tumor3d.segmentation.given_segmentation`); detection
        still runs, nothing trims the mask.
    segmentation_name : str, optional
        Its file name, said in ``measured`` and the notes.
    header_notes : sequence of str
        The reader's notes on the input file's header
        (:func:`tumor3d.storage.readers.handoff.read_noting`), as the ingest stage
        records them: informational, except that the header states no orientation
        (a doubt).
    models : mapping of str to bytes, optional
        The model files of the folder ``segment.learned_models`` names (file name ->
        bytes: :func:`tumor3d.storage.given_models.read_given_models`; :func:`reconstruct`
        reads them), which replace the shipped models; required when it is set.
    """
    from tumor3d.geometry.interpolate import interpolate_stack
    from tumor3d.imaging.preprocess import (
        brain_mask_figures,
        preprocess_volume,
    )
    from tumor3d.learned.bundle import check_models, model_set, uses_models
    from tumor3d.pipeline import tumour_surface
    from tumor3d.segmentation.detect import detect_abnormal_slices
    from tumor3d.segmentation.methods import method_uses_lesion, slices_flagged
    from tumor3d.segmentation.patient import segment_detected
    from tumor3d.simplify import simplify_mesh, target_face_count

    if not isinstance(scan, Scan):
        raise InputError(f"scan must be a tumor3d.imaging.scan.Scan, got {type(scan).__name__}")
    cfg = as_config(config)
    where = cfg.segment.learned_models
    used = segmentation is None and uses_models(cfg.segment.method, scan.modality)
    if where is not None and models is None and used:
        raise InputError(
            f"segment.learned_models names {where!r}: pass its files as models= "
            "(tumor3d.storage.given_models.read_given_models), or call tumor3d.reconstruct"
        )
    chosen = None
    if models is not None:
        source = where or "models"
        check_models(models, source=source)

        def chosen() -> Any:  # the learned method's only
            return model_set(models, scan.modality, cfg.segment.learned_cnn, source=source)

    given = None
    if brain_mask is not None:
        from tumor3d.imaging.brain_mask import binarize_brain_mask

        given = np.asarray(brain_mask)
        if given.shape != scan.shape:
            raise InputError(f"brain_mask has shape {given.shape}, the image {scan.shape}")
        try:  # the checks of a brain mask file (non-finite, empty, off the head)
            given = binarize_brain_mask(given, scan.image)
        except InputError as exc:
            raise InputError(f"brain_mask: {exc}") from None
    tumour_given = None
    if segmentation is not None:
        from tumor3d.segmentation.given_segmentation import binarize_segmentation

        tumour_given = binarize_segmentation(segmentation)
        if tumour_given.shape != scan.shape:
            raise InputError(f"segmentation has shape {tumour_given.shape}, the image {scan.shape}")
    flips = canonical_flips(scan.affine)
    if any(flips):  # the working orientation, the given masks with it
        given, tumour_given = (
            None if a is None else np.ascontiguousarray(reverse_axes(a, scan.affine, flips)[0])
            for a in (given, tumour_given)
        )
        scan = canonical_orientation(scan)
    spacing = scan.spacing_zyx_mm
    affine = np.asarray(scan.affine, dtype=np.float64)
    lr_axis = left_right_axis(affine)
    # preprocess
    pre = preprocess_volume(
        scan.image, **cfg.preprocess.model_dump(), spacing_mm=spacing, brain_mask=given
    )
    brain = np.asarray(pre.brain_mask, dtype=bool)
    exterior = pre.head_exterior
    # detect-abnormal
    det = detect_abnormal_slices(
        pre.enhanced, brain, modality=scan.modality, spacing_mm=spacing, lr_axis=lr_axis,
        **cfg.detect.model_dump(),
    )  # fmt: skip
    if not method_uses_lesion(cfg.segment.method):  # reused only then
        det = dataclasses.replace(det, lesion=None)
    # segment-tumor, as the stage (a given segmentation replaces the method)
    segmented = segment_detected(
        pre.enhanced, brain, det, affine=affine, modality=scan.modality, spacing_mm=spacing,
        lesion=cfg.detect.lesion.model_dump(), head_exterior=exterior,
        image=lambda: scan.image, given=None if tumour_given is None else (tumour_given, affine),
        given_name=segmentation_name, models=chosen, **cfg.segment.model_dump(),
    )  # fmt: skip
    seg, measured = segmented.result, segmented.values["measured"]
    # interpolate-slices, extract-surface, simplify-mesh
    stack = interpolate_stack(
        seg.tumor_mask, **cfg.interpolate.model_dump(), slice_step_mm=scan.slice_step_mm,
        pixel_spacing_mm=scan.pixel_spacing_mm,
    )  # fmt: skip
    fine_affine = stack.fine_affine(affine)
    surface = tumour_surface(stack.mask, fine_affine, **cfg.surface.model_dump())
    simplified = surface
    target = target_face_count(surface.n_faces, cfg.simplify.reduction_percent)
    if not surface.is_empty and target >= 4:  # as the simplify stage: a tetrahedron at least
        simplified = simplify_mesh(surface, **cfg.simplify.model_dump())
    # measure-volume
    dy, dx = scan.pixel_spacing_mm
    slab = slab_height_mm(scan.slice_step_mm, scan.slice_thickness_mm, scan.slice_gap_mm)
    row = measure_volumes(
        seg.tumor_pixels, slices_flagged(seg.method, det.abnormal, seg.tumor_pixels),
        stack.mask, fine_affine, pixel_area_mm2=dy * dx,
        slab_height_mm=slab, mesh=surface, mesh_simplified=simplified,
    ).to_row()  # fmt: skip
    row.update(
        clinical_measures(
            seg.tumor_mask, pixel_spacing_mm=(dy, dx), slab_height_mm=slab,
            mesh_vertices=None if surface.is_empty else surface.vertices,
        )  # fmt: skip
    )
    row.update(slice_thickness_mm=scan.slice_thickness_mm, slice_gap_mm=scan.slice_gap_mm)
    # notes and status (tumor3d.segmentation.review), as the pipeline's
    overlap = slice_overlap_note(scan.slice_step_mm, scan.slice_thickness_mm, scan.slice_gap_mm)
    extraction = "given" if given is not None else str(pre.brain_extraction)
    figures = brain_mask_figures(brain, spacing, extraction, pre.original_u8)
    notes, doubts = run_notes(
        tumour_found=not surface.is_empty,
        caveats=seg.caveats,
        skipped_files=scan.skipped_files,
        brain_mask_note="brain mask given: no skull removal" if given is not None else None,
        **brain_mask_run_notes(figures, seg.method),
        header_notes=[*header_notes, *filter(None, [overlap])],
        slice_order_note=slice_order_note(scan.source_grid),
    )
    if tumour_given is not None:  # informational, as tumor3d.tasks.publish.run_notes
        said = f" ({segmentation_name})" if segmentation_name else ""
        notes.append(f"segmentation: given{said}")
    review = review_status(doubts, segmentation=segmentation_values(seg))
    vols = {k: float(row[f"volume_{k}_mm3"]) for k in VOLUME_KEYS}
    lo, hi = float(row["volume_eq7_ci95_low_mm3"]), float(row["volume_eq7_ci95_high_mm3"])
    return Reconstruction(
        patient_id=scan.patient_id, modality=scan.modality, status=review.status,
        review_reasons=review.reasons, notes=tuple(notes), method=seg.method,
        measured=measured, volumes_mm3=vols,
        volumes_ml={k: v / 1000.0 for k, v in vols.items()},
        eq7_ce=float(row["volume_eq7_ce"]), eq7_ci95_mm3=(lo, hi),
        eq7_ci95_ml=(lo / 1000.0, hi / 1000.0), tumor_mask_slices=np.asarray(seg.tumor_mask),
        brain_mask=brain, affine=affine, tumor_mask=np.asarray(stack.mask),
        fine_affine=fine_affine, mesh=surface, mesh_simplified=simplified, metrics=row,
        scan=scan, tumor_probability=getattr(seg, "probability", None),
    )  # fmt: skip


def reconstruct(
    image: str | os.PathLike[str] | np.ndarray | Scan,
    *,
    affine: np.ndarray | None = None,
    modality: str | None = None,
    config: PipelineConfig | Mapping[str, Any] | str | None = None,
    brain_mask: str | os.PathLike[str] | np.ndarray | None = None,
    segmentation: str | os.PathLike[str] | np.ndarray | None = None,
    patient_id: str | None = None,
    slice_thickness_mm: float | None = None,
    slice_gap_mm: float | None = None,
) -> Reconstruction:
    """Reconstruct one patient's tumour in this process: masks, meshes, volumes, status.

    Parameters
    ----------
    image : path, ndarray or Scan
        A NIfTI, NRRD or MetaImage file, a DICOM series folder or a folder
        of 2-D slices (as ``tumor3d run``); or a 3-D array in its file's voxel
        order ``(i, j, k)`` with ``affine``; or a :class:`~tumor3d.imaging.scan.Scan`.
    affine : (4, 4) ndarray
        With an array: voxel index ``(i, j, k, 1)`` -> RAS mm (as NIfTI;
        nibabel's ``img.affine``). Required then (voxel sizes are never
        assumed); the coarsest axis is the slice axis.
    modality : {"t2", "flair", "t1c"}
        Required (it decides the segmentation method), except for a Scan (its
        own by default) and a folder of slices whose sidecar names it.
    config : PipelineConfig, dict or YAML text, optional
        As ``tumor3d run --config``; the defaults when None.
    brain_mask : path or ndarray, optional
        A brain mask on the image's grid (brain = values > 0.5) used instead
        of skull removal: a file for a path input, an array of the image
        array's shape for an array input. Beside a file, an array is in the
        file's voxel order (nibabel's ``img.get_fdata()``) or on the working
        ``(z, y, x)`` grid, as ``Reconstruction.brain_mask`` is; a nibabel
        array transposed is the latter only for a file stored LPS.
    segmentation : path or ndarray, optional
        Your own tumour mask on the image's grid (tumour = values > 0.5),
        used instead of the segmentation; detection, interpolation, meshes,
        volumes and status run on it (``method`` ``"given"``). A file (same
        shape and affine as the image, checked as ``brain_mask``) or an
        array, as ``brain_mask``.
    patient_id : str, optional
        Default: from the file name, or ``"array"``.
    slice_thickness_mm, slice_gap_mm : float, optional
        Override what the input says about its slices (Eq. 7 uses thickness
        + gap).

    Returns
    -------
    Reconstruction

    Raises
    ------
    InputError
        One line: an unreadable file, no affine with an array, no modality,
        a brain mask or segmentation off the image's grid, an invalid configuration,
        a ``segment.learned_models`` folder without the models it needs.
    """
    if isinstance(image, Scan):
        if modality is not None and _modality(modality, None) != image.modality:
            image = dataclasses.replace(image, modality=_modality(modality, None))
        mask = None if brain_mask is None else np.asarray(brain_mask)
        tumour = None if segmentation is None else np.asarray(segmentation)
        cfg = _resolved(config)
        return reconstruct_scan(
            image, config=cfg, brain_mask=mask, segmentation=tumour,
            models=_given_models(cfg, image.modality, segmentation),
        )  # fmt: skip
    from tumor3d.storage.readers.options import ReadOptions

    if modality is None and isinstance(image, str | os.PathLike):
        from tumor3d.storage.readers import declared_modality

        modality = declared_modality(image)  # a stack's sidecar; None: the error below
    mod = _modality(modality, None)
    cfg = _resolved(config)  # a bad configuration fails before the image is read
    options = ReadOptions(  # the reading options, checked once
        modality=mod, patient_id=patient_id, slice_thickness_mm=slice_thickness_mm,
        slice_gap_mm=slice_gap_mm,
    )  # fmt: skip
    if isinstance(image, np.ndarray):
        for what, given in (("brain_mask", brain_mask), ("segmentation", segmentation)):
            if isinstance(given, str | os.PathLike):
                raise InputError(
                    f"{what} is a path ({given}): with an array image give {what} as an "
                    "array on its grid, or give the image as a file"
                )
        scan = _scan_from_array(image, affine, options)
        mask = None
        if brain_mask is not None:
            arr = np.asarray(brain_mask)
            if arr.shape != image.shape:
                raise InputError(f"brain_mask has shape {arr.shape}, the image {image.shape}")
            mask = scan.source_grid.from_source(arr)
        tumour = None
        if segmentation is not None:
            arr = np.asarray(segmentation)
            if arr.shape != image.shape:
                raise InputError(f"segmentation has shape {arr.shape}, the image {image.shape}")
            tumour = scan.source_grid.from_source(arr)
        return reconstruct_scan(
            scan, config=cfg, brain_mask=mask, segmentation=tumour,
            models=_given_models(cfg, scan.modality, segmentation),
        )  # fmt: skip
    if not isinstance(image, str | os.PathLike):
        raise InputError(
            f"image must be a path, a 3-D array with affine, or a Scan; got {type(image).__name__}"
        )
    if affine is not None:
        raise InputError("affine is for an array input; a file carries its own")
    from tumor3d.storage.readers.handoff import read_noting

    scan, header_notes = read_noting(image, options)  # nibabel's header notes, as ingest's
    mask = None
    if brain_mask is not None:
        if isinstance(brain_mask, np.ndarray):
            mask = _on_scan_grid(brain_mask, scan, "brain_mask")
        else:
            from tumor3d.storage.brain_mask import read_given_brain_mask

            mask = read_given_brain_mask(brain_mask, scan).mask
    tumour, name = None, None
    if isinstance(segmentation, np.ndarray):
        tumour = _on_scan_grid(segmentation, scan, "segmentation")
    elif segmentation is not None:
        from tumor3d.storage.given_segmentation import read_given_segmentation

        given_seg = read_given_segmentation(segmentation, scan)
        tumour, name = given_seg.mask, given_seg.name
    return reconstruct_scan(
        scan,
        config=cfg,
        brain_mask=mask,
        segmentation=tumour,
        segmentation_name=name,
        header_notes=header_notes,
        models=_given_models(cfg, scan.modality, segmentation),
    )


def _resolved(config: PipelineConfig | Mapping[str, Any] | str | None) -> PipelineConfig:
    """The configuration, ``segment.learned_models`` made absolute (said so in provenance)."""
    cfg = as_config(config)
    if cfg.segment.learned_models is None:
        return cfg
    from tumor3d.storage.given_models import resolve_learned_models

    return resolve_learned_models(cfg)


def _given_models(cfg: PipelineConfig, modality: str, segmentation: Any) -> dict[str, bytes] | None:
    """The model files of ``segment.learned_models`` a run of ``modality`` uses (or None).

    None too with a given ``segmentation``: no method runs.
    """
    if cfg.segment.learned_models is None or segmentation is not None:
        return None
    from tumor3d.storage.given_models import models_for

    return models_for(cfg, modality)


def _on_scan_grid(arr: np.ndarray, scan: Scan, what: str) -> np.ndarray:
    """An array given beside a file, in the file's voxel order (first) or the scan's ``(z, y, x)``.

    Raises
    ------
    InputError
        Neither shape; the message gives the file's, as the user sees the image.
    """
    if arr.shape == scan.source_grid.shape:  # the file's voxel order
        return scan.source_grid.from_source(arr)
    if arr.shape == scan.image.shape:
        return arr
    raise InputError(
        f"{what} has shape {arr.shape}, the image {scan.source_grid.shape} (its file's voxel order)"
    )


def _scan_from_array(data: np.ndarray, affine: np.ndarray | None, options: Any) -> Scan:
    """A Scan of an array in its file's voxel order (``options``: a checked ``ReadOptions``)."""
    if affine is None:
        raise InputError(
            "an array input needs its affine= (voxel index -> RAS mm): voxel sizes are never "
            "assumed"
        )
    aff = np.asarray(affine, dtype=np.float64)
    if aff.shape != (4, 4):
        raise InputError(f"affine must be a 4x4 matrix, got shape {aff.shape}")
    if not np.all(np.isfinite(aff)):
        raise InputError("affine must be finite, got NaN or infinity in it")
    if np.linalg.det(aff[:3, :3]) == 0:
        raise InputError(
            "affine must be invertible: its 3x3 part is singular (a voxel axis of length 0 "
            "or two parallel axes)"
        )
    if data.ndim != 3:
        raise InputError(f"image must be a 3-D array, got shape {data.shape}")
    if data.dtype.kind not in "iuf":  # complex: which part?; bool: a mask, not an image
        raise InputError(
            f"image must be an array of real intensities (integers or floats), got dtype "
            f"{data.dtype}" + (": a mask is given as segmentation=" if data.dtype == bool else "")
        )
    from tumor3d.storage.readers.common import scan_from_volume

    return scan_from_volume(
        np.asarray(data, dtype=np.float32), aff, where="array", source="array",
        modality=options.modality, patient_id=options.patient_id or "array",
        slice_thickness_mm=options.slice_thickness_mm, slice_gap_mm=options.slice_gap_mm,
    )  # fmt: skip
