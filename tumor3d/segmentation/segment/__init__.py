"""Tumour segmentation by wavelet + histogram fuzzy c-means (specification section 3).

Arakeri & Reddy (2013) segment each abnormal slice with the "wavelet and
modified FCM" method of their reference [8], whose text could not be
recovered. This module implements the reconstruction recommended by the
specification ([A7], [A8]):

1. one-level Haar DWT of ``J``; its approximation band divided by 2 is the
   2x2 block mean ``LL/2``, whose histogram ``h_LL`` over the brain is
   smoother (less noisy) than that of ``J``;
2. fuzzy c-means on ``h_LL`` with ``C = k`` clusters seeded at the
   histogram peaks of section 2 (cost ``O(G C I)``, independent of the
   number of pixels);
3. every full-resolution brain pixel gets the cluster of maximum
   membership of its gray level;
4. the tumour cluster is the one that matches none of the patient's
   normal-tissue centres; its largest 4-connected component, holes
   filled, is the tumour mask of the slice.

The package: the entry point :func:`segment_tumor` and the robust method here (it looks
``patient_lesion`` up in this namespace), :mod:`~tumor3d.segmentation.segment.result` (what a
method takes and returns), :mod:`~tumor3d.segmentation.segment.definition` (what each mask
holds, which method ``auto`` picks), the paper's method in
:mod:`~tumor3d.segmentation.segment.paper` with its
:mod:`~tumor3d.segmentation.segment.clusters` and :mod:`~tumor3d.segmentation.segment.refine`,
the peer :mod:`~tumor3d.segmentation.segment.multiotsu` and
:mod:`~tumor3d.segmentation.segment.learned`. The methods register in the order paper,
robust, multiotsu, learned. The public names are importable from here.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from typing import Any

import numpy as np

from tumor3d.errors import InputError
from tumor3d.imaging.identity import MODALITIES
from tumor3d.segmentation.detect import SliceDetection
from tumor3d.segmentation.fcm import FCMDiagnostics, fcm_memberships, fuzzy_cmeans_histogram
from tumor3d.segmentation.lesion import lesion_params, patient_lesion
from tumor3d.segmentation.methods import AUTO, check_method_name, method_spec, register_method
from tumor3d.segmentation.segment.clusters import _choose_tumor_cluster as _choose_tumor_cluster
from tumor3d.segmentation.segment.clusters import _tumor_component as _tumor_component
from tumor3d.segmentation.segment.definition import _WHOLE_TUMOUR, lesion_definition, resolve_method
from tumor3d.segmentation.segment.paper import segment_paper
from tumor3d.segmentation.segment.refine import _largest_linked_group as _largest_linked_group
from tumor3d.segmentation.segment.refine import _refine_boundary as _refine_boundary
from tumor3d.segmentation.segment.result import SegmentationResult, _checked_inputs, _slice_result

__all__ = [
    "FCMDiagnostics",
    "SegmentationResult",
    "fuzzy_cmeans_histogram",
    "fcm_memberships",
    "learned_prior",
    "lesion_definition",
    "multiotsu_peer",
    "resolve_method",
    "segment_multiotsu",
    "segment_paper",
    "segment_robust",
    "segment_tumor",
]


def segment_tumor(
    enhanced: np.ndarray,
    brain_mask: np.ndarray,
    detection: SliceDetection,
    *,
    modality: str = "t2",
    method: str = "auto",
    wavelet: str = "haar",
    fuzziness: float = 2.0,
    tol: float = 1e-3,
    max_num_iter: int = 100,
    min_tumor_pixels: int = 20,
    keep_largest_3d_component: bool = True,
    component_tolerance_px: int = 3,
    rim_px: int = 3,
    max_brain_fraction: float = 0.5,
    refine_boundary: bool = True,
    min_tumor_slices: int = 2,
    multiotsu_classes: int = 4,
    lesion: Mapping[str, Any] | None = None,
    spacing_mm: tuple[float, float, float] | None = None,
    lr_axis: int | None = None,
    head_exterior: np.ndarray | None = None,
    image: np.ndarray | None = None,
    model: Any = None,
    learned_cnn: str = "auto",
    cnn: Any = None,
    learned_models: str | None = None,
) -> SegmentationResult:
    """Segment the tumour of a patient's slices (specification section 3).

    The method is looked up in the registry of segmentation methods
    (:mod:`tumor3d.segmentation.methods`) and called with the keywords below
    that it names. The registered ones (``SegmentConfig.method``) follow;
    ``"auto"`` (default) is ``"learned"``
    on FLAIR and T1c (``"robust"`` when ``image`` or ``model`` is not given),
    and on T2 ``"paper"`` where the paper's premise holds (three tissue modes
    on nearly every slice), ``"robust"`` otherwise (:func:`resolve_method`).

    - ``"robust"``: :func:`tumor3d.segmentation.lesion.segment_hyperintense_lesion`,
      patient-pooled normal-tissue model, in-plane smoothing as spatial
      regularisation, 3-D connectivity across slices, partial-volume
      boundary, enclosed core filled; restricted to the slices ``detection``
      flags. The lesion model runs once: ``detection.lesion`` (computed by
      the robust detection) is reused when present, otherwise the model is
      computed here with the keywords ``lesion``. Uses
      ``min_tumor_pixels`` (slices with fewer tumour pixels are cleared).
    - ``"paper"``: the wavelet + histogram FCM of the paper, slice by slice
      (:func:`_segment_paper`, whose docstring lists its steps and the
      robustness deviations controlled by ``rim_px``, ``max_brain_fraction``,
      ``refine_boundary``, ``keep_largest_3d_component``, ...).
    - ``"learned"``: the robust method's mask, then a boosted forest trained
      on labelled patients (:mod:`tumor3d.learned`) that takes it as one of
      its features beside intensity, context, asymmetry and depth on the
      acquired ``image``, and keeps one 3-D lesion of its probability
      (:func:`tumor3d.learned.segment.segment_learned`). Needs ``image`` and
      ``model``; returns the ``probability`` and a ``review``.
    - ``"multiotsu"``: the simple peer: ``multiotsu_classes``-class multi-Otsu
      thresholds of the pooled brain gray levels, the brightest class, its
      largest 26-connected 3-D component (``detection`` is ignored).

    Measured on real data (``benchmarks/real_segmentation.py``, see
    ``reports/segmentation.md``): on BraTS FLAIR and the real T2 case
    emulated at 2 mm / 5 mm the paper method segments nothing, the robust
    method beats the peer on every case (at native 1 mm the peer's 3-D Dice
    is higher on pat0003).

    Parameters
    ----------
    enhanced : (z, y, x) ndarray of uint8
        ``J`` of section 1.
    brain_mask : (z, y, x) ndarray of bool
        ``M_brain`` of section 1.
    detection : SliceDetection
        Section 2 result for the same slices.
    modality : {"t2", "flair", "t1c"}
        Sequence (case-insensitive).
    method : str
        ``"auto"`` or a registered method
        (:func:`tumor3d.segmentation.methods.method_names`); see above.
    wavelet, fuzziness, tol, max_num_iter, min_tumor_pixels, keep_largest_3d_component,
    component_tolerance_px, rim_px, max_brain_fraction, refine_boundary, min_tumor_slices
        Paper-method parameters (see
        :func:`~tumor3d.segmentation.segment.paper.segment_paper`); the robust method uses
        the last three listed above.
    multiotsu_classes : int
        Peer: number of multi-Otsu classes (2-6).
    lesion : mapping, optional
        Robust method without ``detection.lesion``: keywords of
        :func:`tumor3d.segmentation.lesion.segment_hyperintense_lesion` (the fields of
        ``tumor3d.config.LesionConfig``); None = its defaults. Ignored when
        the detection carries the lesion (it was computed with them).
    spacing_mm : (3,) tuple of float, optional
        Voxel spacing ``(slice step, row, column)`` in mm (robust method: the
        depth rule of :mod:`tumor3d.segmentation.lesion`, and the midline caveat, whose
        band is measured in mm from ``detection.lesion.plane``: pass the
        spacing the detection used); None = 1 mm voxels. The adapter passes
        the scan's.
    lr_axis : {1, 2} or None
        Robust method: the left-right array axis (symmetry rule of
        :mod:`tumor3d.segmentation.lesion`, :func:`~tumor3d.segmentation.lesion.left_right_axis`
        of the
        scan's affine); None skips the rule. The adapter passes it.
    head_exterior : (z, y, x) ndarray of bool, optional
        The air outside a raw head (``PreprocessResult.head_exterior``): the
        caveats then say where the tumour comes nearer it than any brain can
        (:func:`tumor3d.segmentation.caveats.scalp_caveat`). None (a skull-stripped
        volume, a given brain mask) skips that caveat.
    image : (z, y, x) ndarray of real numbers, optional
        Learned method: the slices as acquired (the scan's own intensities,
        before equalisation). Not modified.
    model : tumor3d.learned.forest.ForestModel, optional
        Learned method: the trained model (:func:`tumor3d.learned.shipped.shipped_model`).
    learned_cnn : {"auto", "off"}
        Learned method: ``"auto"`` averages the forest's probability with the
        U-Net ``cnn``'s when one is given; ``"off"``: the forest alone.
    cnn : tumor3d.learned.cnn.UNetWeights or a sequence of them, optional
        Learned method: the U-Net (ensemble) of the sequence
        (:func:`tumor3d.learned.shipped.shipped_cnn`; FLAIR only), or None.
    learned_models : str, optional
        Learned method: the folder of a user's own models (``segment.learned_models``),
        which the caller reads (:func:`tumor3d.learned.bundle.model_set`) and gives as
        ``model`` and ``cnn``; set without ``model``, an error (not the rule-based
        method, nor the shipped models, in its place).

    Returns
    -------
    SegmentationResult
        An empty mask (every ``tumor_pixels`` 0) is the documented result for
        a brain without tumour.

    Raises
    ------
    InputError
        On wrong dimensions, dtypes or shapes, a detection of another length,
        an unknown modality, method or wavelet, or an out-of-range parameter.
    """
    check_method_name(method)  # "auto" or a registered method; else an error naming them
    requested = method
    method = resolve_method(
        method, modality, detection if isinstance(detection, SliceDetection) else None
    )
    if method == "learned" and model is None and learned_models is not None:
        raise InputError(
            f"segment.learned_models names {learned_models!r} but no model was given: pass "
            "its models (tumor3d.learned.bundle.model_set) as model= and cnn="
        )
    if method == "learned" and requested == AUTO and (image is None or model is None):
        method = "robust"  # "auto" without the acquired image or a model: the rule-based one
    spec = method_spec(method)
    mod = modality.strip().lower() if isinstance(modality, str) else modality
    if mod in MODALITIES and mod not in spec.modalities:
        raise InputError(
            f"the {method} method does not segment {mod}: it takes {', '.join(spec.modalities)}"
        )
    keywords = {
        "modality": modality, "wavelet": wavelet, "fuzziness": fuzziness, "tol": tol,
        "max_num_iter": max_num_iter, "min_tumor_pixels": min_tumor_pixels,
        "keep_largest_3d_component": keep_largest_3d_component,
        "component_tolerance_px": component_tolerance_px, "rim_px": rim_px,
        "max_brain_fraction": max_brain_fraction, "refine_boundary": refine_boundary,
        "min_tumor_slices": min_tumor_slices, "multiotsu_classes": multiotsu_classes,
        "lesion": lesion, "spacing_mm": spacing_mm, "lr_axis": lr_axis,
        "head_exterior": head_exterior, "image": image, "model": model,
        "learned_cnn": learned_cnn, "cnn": cnn,
    }  # fmt: skip
    result = spec.fn(enhanced, brain_mask, detection, **spec.arguments(keywords))
    return result if result.method == method else replace(result, method=method)


@register_method(
    "robust",
    description="the patient-pooled normal-tissue model grown in 3-D "
    "(tumor3d.segmentation.lesion), kept on the abnormal slices",
    measures={
        "flair": _WHOLE_TUMOUR.format(seq="FLAIR"),
        "t2": _WHOLE_TUMOUR.format(seq="T2"),
        "t1c": (
            "enhancing tumour: the contrast-enhancing lesion with its enclosed necrotic core "
            "(no oedema)"
        ),
    },
    uses_lesion=True,
)
def segment_robust(
    enhanced: np.ndarray,
    brain_mask: np.ndarray,
    detection: SliceDetection,
    *,
    modality: str,
    min_tumor_pixels: int,
    lesion: Mapping[str, Any] | None,
    spacing_mm: tuple[float, float, float] | None,
    lr_axis: int | None,
    head_exterior: np.ndarray | None,
) -> SegmentationResult:
    """The robust method: the detection's lesion model (computed here if absent) on its slices."""
    img, brain, mod = _checked_inputs(enhanced, brain_mask, detection, modality, min_tumor_pixels)
    nz = img.shape[0]
    params = lesion_params(lesion)
    res = detection.lesion
    if res is None:
        res = patient_lesion(
            img, brain, modality=mod, lesion=lesion, spacing_mm=spacing_mm, lr_axis=lr_axis
        )
    elif res.mask.shape != img.shape:
        raise InputError(
            f"detection.lesion has shape {res.mask.shape} but enhanced has {img.shape}"
        )
    # the lesion on the abnormal slices only (a copy: the detection's mask is kept)
    tumor = res.mask & np.asarray(detection.abnormal, dtype=bool)[:, None, None]
    return _slice_result(
        tumor,
        detection,
        how="lesion",
        center=np.full(nz, res.lesion_gray),
        ref=np.array([res.model.median, res.model.sigma, res.model.seed_threshold]),
        min_tumor_pixels=min_tumor_pixels,
        method="robust",
        caveat_keywords={
            "plane": res.plane,
            "spacing_mm": spacing_mm,
            "min_region_mm2": params["min_region_mm2"],
            "min_slices": params["min_slices"],
            "midline_lesion": res.midline,
            "head_exterior": head_exterior,
        },
    )


# registered after segment_robust and in this order: the registry lists the methods in the
# order they register (paper, robust, multiotsu, learned)
from tumor3d.segmentation.segment.multiotsu import multiotsu_peer, segment_multiotsu  # noqa: E402

# isort: split
from tumor3d.segmentation.segment.learned import learned_prior  # noqa: E402
