"""One patient's tumour segmentation, as the segment-tumor stage stores it.

:func:`segment_patient` is the stage's core function: from the preprocess and
detect stages' products (the enhanced slices, the brain mask, the head's
exterior, the per-slice detection and the record of the lesion model) to what
the stage stores: the tumour mask and its affine, the per-slice table, the
probability map (learned method) and the stage's values. A segmentation the
user gave replaces the method (:mod:`tumor3d.segmentation.given_segmentation`).

The values: the tumour's pixel and slice counts, the caveats, the modality,
the method that ran (``segment_method``), what its mask holds in words
(``measured``) and, for the learned method, its models (``segment_model``:
``"forest"`` or ``"forest + U-Net mean"``), its review (``needs_review``,
``review_reasons``, ``quality_score``, ``review_figures``, read by
:func:`tumor3d.segmentation.review.review_status`) and the shipped models'
identity (:func:`tumor3d.learned.shipped.model_identity`).

Arrays in, results out. The two inputs a method may not need (the acquired
image, the lesion model's mask) are passed as functions returning them and
called only when used; the learned method's shipped models are read from the
package (:func:`tumor3d.learned.shipped.shipped_models`) only when it runs.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from tumor3d.errors import InputError
from tumor3d.learned.bundle import ModelSet
from tumor3d.learned.shipped import model_identity, shipped_models
from tumor3d.segmentation.detect import SliceDetection
from tumor3d.segmentation.given_segmentation import given_definition, given_segmentation
from tumor3d.segmentation.lesion import LesionResult, MirrorPlane, NormalModel, left_right_axis
from tumor3d.segmentation.methods import method_spec, method_uses_lesion, slices_flagged
from tumor3d.segmentation.segment import (
    SegmentationResult,
    lesion_definition,
    resolve_method,
    segment_tumor,
)

__all__ = [
    "PatientSegmentation",
    "lesion_from_record",
    "method_models",
    "review_values",
    "segment_detected",
    "segment_model",
    "segment_patient",
    "slice_records",
    "stored_detection",
]


@dataclass(frozen=True, eq=False)
class PatientSegmentation:
    """What :func:`segment_patient` returns: everything the segment-tumor stage stores.

    Attributes
    ----------
    result : SegmentationResult
        The segmentation (``tumor_mask``, ``probability`` for the learned method).
    affine : (4, 4) ndarray
        The affine of ``result``'s arrays: the given mask's, else the enhanced slices'.
    records : list of dict
        The per-slice table (:func:`slice_records`).
    values : dict
        The stage's values (JSON-able; see the module's docstring).
    """

    result: SegmentationResult
    affine: np.ndarray
    records: list[dict[str, Any]]
    values: dict[str, Any]


def _f(v: Any, missing: float = float("nan")) -> float:
    return missing if v is None else float(v)


def _json_float(v: float) -> float | None:
    """A figure as JSON allows it (None for inf and NaN).

    >>> _json_float(0.25), _json_float(float("nan")), _json_float(float("inf"))
    (0.25, None, None)
    """
    v = float(v)
    return v if np.isfinite(v) else None


def lesion_from_record(mask: np.ndarray, meta: Mapping[str, Any]) -> LesionResult | None:
    """The :class:`LesionResult` the detect stage stored (mask and record), None if not computed.

    ``meta``: the record the detect stage writes beside the mask
    (``tumor3d.tasks.detect.lesion_metadata``: ``computed``, the normal model's
    scalars, the mirror plane, ``midline``), JSON's None standing for NaN
    and, for ``csf_threshold``, infinity.
    """
    if not meta.get("computed"):
        return None
    model = NormalModel(
        _f(meta["median"]),
        _f(meta["sigma"]),
        _f(meta["seed_threshold"]),
        _f(meta["csf_threshold"], float("inf")),
    )
    plane = meta.get("mirror_plane")
    return LesionResult(
        np.asarray(mask, dtype=bool),
        model,
        _f(meta["lesion_gray"]),
        _f(meta["grow_threshold"]),
        int(meta["n_components"]),
        None
        if plane is None
        else MirrorPlane(int(plane["lr_axis"]), float(plane["yaw_deg"]), float(plane["offset_mm"])),
        bool(meta.get("midline", False)),  # absent from artifacts written before step 3f
    )


def stored_detection(
    records: Iterable[Mapping[str, Any]],
    lesion: Mapping[str, Any],
    lesion_mask: Callable[[], np.ndarray],
    *,
    with_lesion: bool = True,
) -> SliceDetection:
    """The detect stage's :class:`SliceDetection` from its per-slice ``records``.

    With ``with_lesion``, the lesion model it computed (if it did: ``lesion``,
    its record, says so) is put back on the detection (``lesion_mask()`` is
    then called for its mask), so the robust method does not compute it again.
    """
    det = SliceDetection.from_records(list(records))
    if with_lesion and lesion.get("computed"):
        det = dataclasses.replace(det, lesion=lesion_from_record(lesion_mask(), lesion))
    return det


def slice_records(result: SegmentationResult, detected: Any) -> list[dict[str, Any]]:
    """The per-slice table: :meth:`SegmentationResult.to_records` and ``flagged``.

    ``flagged``: the slices the method flags abnormal
    (:func:`tumor3d.segmentation.methods.slices_flagged`: the detection's,
    ``detected``, for a method that segments those, else the slices with tumour).
    """
    flags = slices_flagged(result.method, detected, result.tumor_pixels)
    return [{**r, "flagged": bool(f)} for r, f in zip(result.to_records(), flags, strict=True)]


def segment_model(method: str, cnn: Any, folder: str | None = None) -> str:
    """Which models made the mask, in words: the learned method's, else ``""``.

    ``folder``: where a user's own models came from (``segment.learned_models``).

    >>> segment_model("robust", None), segment_model("learned", None)
    ('', 'forest')
    >>> segment_model("learned", ("unet",))
    'forest + U-Net mean'
    >>> segment_model("learned", None, "/data/mine")
    'forest, models of /data/mine'
    """
    if method != "learned":
        return ""
    words = "forest" if cnn is None else "forest + U-Net mean"
    return words if folder is None else f"{words}, models of {folder}"


def review_values(review: Any) -> dict[str, Any]:
    """A method's own review (:class:`tumor3d.learned.review.Review`) as the stage's values.

    ``needs_review``, ``review_reasons``, ``quality_score`` and
    ``review_figures`` (a non-finite figure as None), JSON-able.
    """
    return {
        "needs_review": bool(review.needs_review),
        "review_reasons": list(review.reasons),
        "quality_score": float(review.quality_score),
        "review_figures": {k: _json_float(v) for k, v in review.figures.items()},
    }


def segment_patient(
    enhanced: np.ndarray,
    brain_mask: np.ndarray,
    detection: Sequence[Mapping[str, Any]],
    *,
    affine: np.ndarray,
    modality: str,
    spacing_mm: tuple[float, float, float],
    lesion: Mapping[str, Any],
    lesion_mask: Callable[[], np.ndarray],
    head_exterior: np.ndarray,
    image: Callable[[], np.ndarray],
    given: Iterable[np.ndarray] | None = None,
    given_name: str | None = None,
    method: str = "auto",
    learned_cnn: str = "auto",
    **keywords: Any,
) -> PatientSegmentation:
    """One patient's tumour segmentation and everything the segment-tumor stage stores of it.

    Parameters
    ----------
    enhanced, brain_mask : (z, y, x) ndarray
        The preprocess stage's ``J`` and brain mask.
    detection : sequence of mapping
        The detect stage's per-slice records (:meth:`SliceDetection.to_records`).
    affine : (4, 4) ndarray
        ``enhanced``'s affine (its left-right axis: the robust method's symmetry rule).
    modality : str
        The scan's sequence.
    spacing_mm : (3,) tuple of float
        Voxel spacing ``(slice step, row, column)``.
    lesion : mapping
        The detect stage's record of the lesion model (``computed``, its
        scalars, ``params``: the ``detect.lesion`` keywords it ran with).
    lesion_mask : callable
        Returns the lesion model's mask; called only when the model was
        computed and the method may reuse it (:func:`stored_detection`).
    head_exterior : (z, y, x) ndarray
        The air outside a raw head (all False for a skull-stripped one: no scalp caveat).
    image : callable
        Returns the acquired slices; called only for a method that needs them
        with its model (the learned one).
    given : (mask, affine), optional
        A segmentation the user gave, on the scan's grid: it replaces the
        method (``segment_method`` ``"given"``), stored as given with its affine.
    given_name : str, optional
        Its file name (``measured`` names it).
    method, learned_cnn, **keywords
        The ``segment`` configuration (:class:`tumor3d.config.SegmentConfig`):
        passed to :func:`tumor3d.segmentation.segment.segment_tumor`, except
        ``learned_models`` and ``models`` (:func:`segment_detected`).

    Returns
    -------
    PatientSegmentation
    """
    with_lesion = given is None and method_uses_lesion(method)
    det = stored_detection(detection, lesion, lesion_mask, with_lesion=with_lesion)
    return segment_detected(
        enhanced, brain_mask, det, affine=affine, modality=modality, spacing_mm=spacing_mm,
        lesion=lesion["params"], head_exterior=head_exterior, image=image, given=given,
        given_name=given_name, method=method, learned_cnn=learned_cnn, **keywords,
    )  # fmt: skip


def method_models(
    method: str,
    modality: str,
    detection: SliceDetection | None,
    image: Callable[[], np.ndarray],
    learned_cnn: str = "auto",
    models: ModelSet | Mapping[str, Any] | Callable[[], ModelSet] | None = None,
    learned_models: str | None = None,
) -> dict[str, Any]:
    """``segment_tumor``'s ``image``, ``model`` and ``cnn`` keywords, where the method needs them.

    The learned method (``method`` as resolved for ``modality`` and ``detection``) gets
    the acquired slices (``image()``, called only then) and the ``model`` and ``cnn`` of
    ``models`` (a user's own, :func:`tumor3d.learned.bundle.model_set`, or a callable
    returning them, called only then; or a mapping of the two: the benchmarks'
    out-of-fold models), by default the shipped ones
    (:func:`tumor3d.learned.shipped.shipped_models`: with ``learned_cnn`` auto, the
    shipped U-Net of the sequence, if any), except where ``learned_models`` names a
    user's folder: then ``models`` must be given (an :class:`InputError`, never the
    shipped models in their place); every other method gets nothing (``{}``). The
    segment stage's rule, for whoever runs the segmentation from arrays
    (:func:`segment_detected`, the benchmarks' harness).

    >>> method_models("robust", "flair", None, image=lambda: 1 / 0)
    {}
    """
    if not method_spec(resolve_method(method, modality, detection)).needs_model:
        return {}
    if models is None and learned_models is not None:
        raise InputError(
            f"segment.learned_models names {learned_models!r} but no model was given: pass "
            "its models (tumor3d.learned.bundle.model_set) as models="
        )
    if models is None:
        chosen = shipped_models(modality, learned_cnn)
    else:
        chosen = models() if callable(models) else models
    keywords = chosen.keywords() if isinstance(chosen, ModelSet) else dict(chosen)
    return {"image": image(), **keywords}


def segment_detected(
    enhanced: np.ndarray,
    brain_mask: np.ndarray,
    detection: SliceDetection,
    *,
    affine: np.ndarray,
    modality: str,
    spacing_mm: tuple[float, float, float],
    lesion: Mapping[str, Any],
    head_exterior: np.ndarray | None,
    image: Callable[[], np.ndarray],
    given: Iterable[np.ndarray] | None = None,
    given_name: str | None = None,
    method: str = "auto",
    learned_cnn: str = "auto",
    models: ModelSet | Callable[[], ModelSet] | None = None,
    **keywords: Any,
) -> PatientSegmentation:
    """:func:`segment_patient` from a detection in memory (:func:`tumor3d.reconstruct`'s too).

    ``detection`` is the per-slice detection with the lesion model it computed
    (``detection.lesion``, None when not computed or not reused); ``lesion``
    the ``detect.lesion`` keywords; ``head_exterior`` the air outside a raw head
    (None or all False for a skull-stripped one: no scalp caveat). ``models``: the
    learned method's models for ``modality`` when they are a user's own (the folder
    ``segment.learned_models`` names, read by the caller:
    :func:`tumor3d.learned.bundle.model_set`; or a callable returning them, called once
    and only if the learned method runs); None: the shipped ones (with
    ``learned_models`` set, an error: :func:`method_models`).
    The other parameters are :func:`segment_patient`'s.
    """
    if callable(models):
        models = functools.cache(models)
    det = detection
    if given is not None:
        mask, mask_affine = given
        result = given_segmentation(np.asarray(mask).astype(bool), spacing_mm=spacing_mm)
        return PatientSegmentation(
            result,
            mask_affine,
            slice_records(result, det.abnormal),
            _values(result, modality, given_definition(given_name)),
        )
    learned = method_models(
        method, modality, det, image, learned_cnn, models, keywords.get("learned_models")
    )
    exterior = None if head_exterior is None else np.asarray(head_exterior).astype(bool)
    result = segment_tumor(
        enhanced,
        brain_mask,
        det,
        modality=modality,
        spacing_mm=spacing_mm,
        lr_axis=left_right_axis(affine),
        lesion=dict(lesion),
        # the air outside a raw head (none stored for a skull-stripped one): scalp caveat
        head_exterior=exterior if exterior is not None and exterior.any() else None,
        method=method,
        learned_cnn=learned_cnn,
        **keywords,
        **learned,
    )
    cnn = learned.get("cnn") if result.method == "learned" else None
    review: dict[str, Any] = {}
    if result.review is not None:  # read by tumor3d.segmentation.review.review_status
        files = models() if callable(models) else models
        identity = model_identity(modality, learned["model"], cnn, files=files)
        review = {**review_values(result.review), **identity}
    definition = lesion_definition(result.method, modality)
    folder = keywords.get("learned_models") if models is not None else None
    values = _values(result, modality, definition, cnn, folder)
    return PatientSegmentation(result, affine, slice_records(result, det.abnormal), review | values)


def _values(
    result: SegmentationResult,
    modality: str,
    measured: str,
    cnn: Any = None,
    folder: str | None = None,
) -> dict[str, Any]:
    """The stage's values every segmentation has."""
    return {
        "tumor_pixels_total": int(np.sum(result.tumor_pixels)),
        "n_tumor_slices": int(np.count_nonzero(result.tumor_pixels)),
        # where the volume may be wrong, in words (the run's notes say them)
        "caveats": list(result.caveats),
        # which method ran and what its mask (every volume) holds, in words
        "modality": modality,
        "segment_method": result.method,
        "measured": measured,
        "segment_model": segment_model(result.method, cnn, folder),
    }
