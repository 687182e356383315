"""The paper's method: per-slice wavelet + histogram fuzzy c-means (``segment.method: paper``).

:func:`_segment_paper` runs the steps of specification section 3 ([A7],
[A8]) in order: the ``LL/2`` histograms and the patient's reference centres
(:mod:`~tumor3d.segmentation.segment.clusters`), then on each abnormal slice
the clusters (:func:`_slice_clusters`, steps 2-4) and the mask
(:func:`_slice_mask`, step 5), then the 3-D consistency across slices
(:func:`_keep_linked_tumour`, :mod:`~tumor3d.segmentation.segment.refine`).

The paper's configuration (``configs/paper.yaml``) keeps the literal step 5
(``rim_px=0``) and takes ``refine_boundary``, ``max_brain_fraction=0.5`` and
``keep_largest_3d_component``, each measured on the T2 phantoms of
``reports/PAPER.md`` (seeds 0-7, tumour-free 0-3; ``make paper``) by
reverting it alone: with pixels labelled by their cluster ([A8] literally)
Eq. 9 is 3.2 % on average and 5.4 % per slice (0.80 % and 2.05 % with the
boundary decided by partial volume); without the brain-fraction check 6 of
64 tumour slices are lost (the largest linked group is then an end slice's
partial volume); slice by slice, 16 of 185 normal slices keep a false
tumour and 5 tumour tips are missed. With all three, every tumour slice and
no normal slice is reported and Eq. 7 lies within 1.31 % of the truth.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np

from tumor3d.errors import InputError
from tumor3d.imaging.identity import MODALITIES
from tumor3d.segmentation.caveats import segmentation_caveats
from tumor3d.segmentation.detect import SliceDetection, _check_pair
from tumor3d.segmentation.detect.methods import PAPER_PREMISE_FRACTION, paper_premise_share
from tumor3d.segmentation.fcm import _check_fcm_params, _fcm_histogram, fcm_memberships
from tumor3d.segmentation.methods import register_method
from tumor3d.segmentation.segment.clusters import (
    _choose_tumor_cluster,
    _ll_histograms,
    _reference_centers,
    _tumor_component,
)
from tumor3d.segmentation.segment.refine import (
    _extend_tips,
    _largest_linked_group,
    _refine_boundary,
)
from tumor3d.segmentation.segment.result import N_GRAY, SegmentationResult


def _segment_paper(
    img: np.ndarray, brain: np.ndarray, detection: SliceDetection, p: _PaperParams
) -> SegmentationResult:
    """The paper's segmentation (``method="paper"``, specification section 3).

    For each slice flagged abnormal by ``detection`` with ``k`` modes:

    1. [A7] ``h_LL`` = histogram of the Haar ``LL/2`` band (the 2x2 block
       mean) over the 2x2 blocks entirely in the brain (:func:`_ll_histograms`);
    2. histogram FCM with ``C = k``, ``m = fuzziness``, seeded at section 2's peaks;
    3. each brain pixel of ``J`` takes the cluster of maximum membership of its gray;
    4. [A8] the tumour is the cluster matching none of the patient's reference
       centres (:func:`_reference_centers`: FCM, ``C = 3``, on the slices that
       are not abnormal), else the modality rule (steps 2-4: :func:`_slice_clusters`);
    5. mask = largest 4-connected component of the tumour cluster, holes filled,
       dropped if smaller than ``min_tumor_pixels`` (:func:`_slice_mask`).

    Deviations (robustness on real data, not in the specification), each
    described and measured where it is made: the tumour cluster's
    plausibility and T2's CSF pinned (:func:`_slice_clusters`); the brain
    rim (``rim_px``), the boundary (``refine_boundary``) and the brain
    fraction (``max_brain_fraction``) (:func:`_slice_mask`); the 3-D
    consistency (``keep_largest_3d_component``, ``component_tolerance_px``,
    ``min_tumor_slices``) and the tips (:func:`_keep_linked_tumour`). The
    module docstring gives what each gains in the paper's configuration.

    Parameters
    ----------
    img, brain : (z, y, x) ndarray
        ``J`` (uint8) and ``M_brain`` (bool), checked by :func:`_checked_paper_inputs`.
    detection : SliceDetection
        Section 2 result for the same slices (``k`` and the seeds).
    p : _PaperParams
        The checked parameters (:func:`segment_paper` describes them).

    Returns
    -------
    SegmentationResult
    """
    hists = _ll_histograms(img, brain)  # step 1 [A7]: h_LL of every slice
    # step 4 [A8]: the reference centres, from the slices that are not abnormal
    ref = _reference_centers(hists[~detection.abnormal].sum(axis=0), p.m, p.tol, p.max_num_iter)
    out = _SliceRecords.empty(img.shape)
    for z in np.flatnonzero(detection.abnormal):  # steps 2-5 on each abnormal slice
        _segment_slice(out, z, img[z], brain[z], hists[z], detection.peaks_gray[z], ref, p)
    if p.keep_largest_3d_component:
        _keep_linked_tumour(out, img, brain, p)
    return out.result(ref)


@dataclass(frozen=True)
class _PaperParams:
    """The parameters of :func:`_segment_paper` (``m`` is ``fuzziness``), checked when made.

    Normalised to their types; :class:`~tumor3d.errors.InputError` on the first one
    found wrong (:func:`segment_paper` describes them).
    """

    modality: str
    m: float
    tol: float
    max_num_iter: int
    min_tumor_pixels: int
    keep_largest_3d_component: bool
    component_tolerance_px: int
    rim_px: int
    max_brain_fraction: float
    refine_boundary: bool
    min_tumor_slices: int

    def __post_init__(self) -> None:
        mod = self.modality.strip().lower() if isinstance(self.modality, str) else self.modality
        if mod not in MODALITIES:
            raise InputError(f"unknown modality {self.modality!r}: expected one of {MODALITIES}")
        _check_fcm_params(self.m, self.tol, self.max_num_iter)
        for name in ("min_tumor_pixels", "min_tumor_slices"):
            if int(getattr(self, name)) < 1:
                raise InputError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not 0.0 < float(self.max_brain_fraction) <= 1.0:
            raise InputError(
                f"max_brain_fraction must lie in (0, 1], got {self.max_brain_fraction}"
            )
        for name in ("rim_px", "component_tolerance_px"):
            if int(getattr(self, name)) < 0:
                raise InputError(f"{name} must be >= 0, got {getattr(self, name)}")
        norm = {"modality": mod, "m": float(self.m), "tol": float(self.tol)}
        norm["max_brain_fraction"] = float(self.max_brain_fraction)
        for name in (
            "max_num_iter",
            "min_tumor_pixels",
            "component_tolerance_px",
            "rim_px",
            "min_tumor_slices",
        ):
            norm[name] = int(getattr(self, name))
        for name, value in norm.items():
            object.__setattr__(self, name, value)


def _checked_paper_inputs(
    enhanced: np.ndarray, brain_mask: np.ndarray, detection: SliceDetection, wavelet: str
) -> tuple[np.ndarray, np.ndarray]:
    """``J`` as uint8 and ``M_brain`` as bool, checked against ``detection`` and the wavelet.

    Raises :class:`~tumor3d.errors.InputError` on the first input found wrong
    (see :func:`segment_paper`).
    """
    img, brain = _check_pair(enhanced, brain_mask)
    if not isinstance(detection, SliceDetection):
        raise InputError("detection must be a SliceDetection")
    if len(detection) != img.shape[0]:
        raise InputError(f"detection has {len(detection)} slices but enhanced has {img.shape[0]}")
    if wavelet != "haar":
        raise InputError(f"unsupported wavelet {wavelet!r}: only 'haar' is implemented")
    return img, brain


@dataclass
class _SliceRecords:
    """Per-slice outcome of :func:`_segment_paper`, filled slice by slice.

    ``centers`` maps each slice where a tumour cluster was chosen to its FCM
    centres and the tumour cluster's index (the tips of
    :func:`_keep_linked_tumour` start from them).
    """

    tumor: np.ndarray
    center_gray: np.ndarray
    selection: np.ndarray
    fcm_iter: np.ndarray
    fcm_conv: np.ndarray
    centers: dict[int, tuple[np.ndarray, int]] = field(default_factory=dict)

    @classmethod
    def empty(cls, shape: tuple[int, ...]) -> _SliceRecords:
        """No tumour, no FCM run, on every slice of a ``(z, y, x)`` volume."""
        nz = shape[0]
        return cls(
            tumor=np.zeros(shape, dtype=bool),
            center_gray=np.full(nz, np.nan),
            selection=np.full(nz, "", dtype=object),
            fcm_iter=np.full(nz, -1, dtype=np.int64),
            fcm_conv=np.zeros(nz, dtype=bool),
        )

    def result(self, ref: np.ndarray) -> SegmentationResult:
        """The records as a :class:`SegmentationResult` with the reference centres ``ref``."""
        return SegmentationResult(
            tumor_mask=self.tumor,
            tumor_pixels=self.tumor.sum(axis=(1, 2)).astype(np.int64),
            reference_centers=ref,
            tumor_center_gray=self.center_gray,
            selection=np.array(self.selection.tolist(), dtype=str),
            fcm_iterations=self.fcm_iter,
            fcm_converged=self.fcm_conv,
        )


def _segment_slice(
    out: _SliceRecords,
    z: int,
    img: np.ndarray,
    brain: np.ndarray,
    hist: np.ndarray,
    seeds: np.ndarray,
    ref: np.ndarray,
    p: _PaperParams,
) -> None:
    """Steps 2-5 on the abnormal slice ``z`` (``img``, ``brain``: its ``J`` and ``M_brain``).

    ``hist`` is the slice's ``h_LL`` (step 1) and ``seeds`` its section 2
    peaks. Records in ``out`` the FCM run, how the tumour cluster was chosen
    and the slice's mask: ``"none"`` without seeds, histogram, plausible
    cluster or large enough component, ``"partial-volume"`` for a component
    covering too much of the brain (:func:`_slice_mask`).
    """
    if seeds.size == 0 or not hist.sum() > 0:
        out.selection[z] = "none"
        return
    cl = _slice_clusters(img, brain, hist, seeds, ref, p)
    out.fcm_iter[z] = cl.n_iter
    out.fcm_conv[z] = cl.converged
    out.selection[z] = cl.how
    if cl.tumor < 0:
        return
    out.centers[z] = (cl.centers, cl.tumor)
    cluster = brain & (cl.label_of_gray[img] == cl.tumor)
    mask, rejected = _slice_mask(cluster, img, brain, float(cl.centers[cl.tumor]), p)
    if rejected:
        out.selection[z] = rejected
        return
    out.tumor[z] = mask
    out.center_gray[z] = cl.centers[cl.tumor]


class _Clusters(NamedTuple):
    """One slice's FCM clusters and its tumour cluster (:func:`_slice_clusters`)."""

    centers: np.ndarray  # (k,) FCM centres v, gray levels
    label_of_gray: np.ndarray  # (256,) cluster of maximum membership of each gray level
    tumor: int  # index of the tumour cluster in ``centers``; -1 for none
    how: str  # how it was chosen: "reference", "rule" or "none"
    n_iter: int  # FCM iterations
    converged: bool  # whether the FCM reached ``tol``


def _slice_clusters(
    img: np.ndarray,
    brain: np.ndarray,
    hist: np.ndarray,
    seeds: np.ndarray,
    ref: np.ndarray,
    p: _PaperParams,
) -> _Clusters:
    """Steps 2-4 on one slice: FCM clusters, labelled gray levels, tumour cluster.

    2. histogram FCM (:func:`~tumor3d.segmentation.fcm.fuzzy_cmeans_histogram`)
       of the slice's ``h_LL`` (``hist``) with ``C = k`` clusters, ``m``
       and the peak gray levels of section 2 (``seeds``) as seeds;
    3. each full-resolution brain pixel of ``J`` (``img``) takes the cluster
       of maximum membership of its gray level;
    4. [A8] the reference centres ``r`` (3, ascending; ``ref``) come from FCM
       with ``C = 3`` on the pooled ``h_LL`` of all the patient's slices that
       are *not* abnormal (seeded at the 1/6, 1/2 and 5/6 quantiles). The
       slice's centres are matched to ``r`` by the Hungarian algorithm on
       ``|v - r|``; the tumour is the unmatched cluster farthest from all
       references (or, with several unmatched, the most populous one: see
       :func:`_choose_tumor_cluster`). Without references (no normal slice)
       the modality rule applies: T2 second-brightest cluster (WM < GM <
       tumour < CSF), FLAIR and T1c brightest cluster.

    Deviations (robustness on real data, not in the specification):

    - Plausibility: a cluster is accepted as tumour only if its centre is
      brighter than the middle reference (GM on T2 and T1c), or than all
      references on FLAIR, where the lesion is the hyperintensity. On real
      data a slice flagged abnormal because of an extra dark mode (partial
      volume, CSF, necrosis) otherwise yields a dark "tumour".
    - If no unmatched cluster is plausible (always the case when ``k <= 3``,
      e.g. with ``abnormal_min_modes=3``, since the assignment then matches
      every cluster), the plausible cluster farthest from the references is
      taken, provided it lies farther than half the smallest gap between
      adjacent references from every reference (otherwise it *is* a normal
      tissue). With no such cluster the slice gets an empty mask
      (``selection == "none"``).
    - T2 and CSF: a cluster at or above the CSF reference is pinned to CSF
      in the assignment (nothing in the brain is brighter than CSF on T2).
      The CSF reference is pulled down by partial volume of the thin CSF
      rim; unpinned, real CSF was left unmatched and taken as tumour.
    """
    v, diag = _fcm_histogram(hist, seeds, p.m, p.tol, p.max_num_iter)
    gray = np.arange(N_GRAY, dtype=np.float64)
    label_of_gray = np.argmax(fcm_memberships(gray, v, p.m), axis=0)
    pixel_hist = np.bincount(img[brain], minlength=N_GRAY)
    mass = np.bincount(label_of_gray, weights=pixel_hist, minlength=v.size)
    t, how = _choose_tumor_cluster(v, ref, p.modality, mass)
    return _Clusters(v, label_of_gray, t, how, diag.n_iter, diag.converged)


def _slice_mask(
    cluster: np.ndarray, img: np.ndarray, brain: np.ndarray, tumor_gray: float, p: _PaperParams
) -> tuple[np.ndarray, str]:
    """Step 5: the tumour mask of one slice and why it is refused (``""``: kept).

    The largest 4-connected component of the tumour ``cluster`` (brain
    pixels), holes filled (:func:`_tumor_component`); refused as ``"none"``
    if smaller than ``min_tumor_pixels``. ``tumor_gray`` is the tumour
    cluster's FCM centre.

    Deviations (robustness on real data, not in the specification):

    - Brain rim (``rim_px``): the tumour component is chosen among
      cluster pixels at least ``rim_px`` inside the brain mask and then
      regains its own pixels near the rim. Where a thick slice cuts the
      brain surface obliquely, CSF and grey matter average to a
      tumour-like gray along the boundary; that rim, hole-filled, became a
      disc covering most of the brain (measured on the phantoms: 2832 of
      4141 brain pixels on a slice).
    - Boundary (``refine_boundary``): FCM labels a pixel half tumour, half
      white matter as grey matter (its gray lies between the two), so the
      mask shrinks wherever the tumour borders white matter: -8 % of the
      pixels of a 27 mm phantom tumour. Pixels touching the mask are
      re-decided by partial volume (:func:`_refine_boundary`).
    - Brain fraction (``max_brain_fraction``): a component covering more than
      this fraction of the slice's brain is the partial volume of a slice
      cutting the brain surface nearly tangentially (at the base and the
      vertex), not a tumour; it is refused as ``"partial-volume"``.
      Measured on the phantoms: 3348 of 4701 brain pixels on such a slice.
    """
    mask = _tumor_component(cluster, brain, p.rim_px)
    if p.refine_boundary and mask.any():
        mask = _refine_boundary(mask, img, brain, tumor_gray)
    if mask.sum() < p.min_tumor_pixels:
        return mask, "none"
    if mask.sum() > p.max_brain_fraction * brain.sum():
        return mask, "partial-volume"
    return mask, ""


def _keep_linked_tumour(
    out: _SliceRecords, img: np.ndarray, brain: np.ndarray, p: _PaperParams
) -> None:
    """3-D consistency: the largest linked group of slice masks, and its tips (in ``out``).

    Deviations (robustness on real data, not in the specification), with
    ``keep_largest_3d_component``:

    - 3-D consistency: the slice masks are linked across consecutive slices
      where they overlap once each is dilated in-plane by
      ``component_tolerance_px`` (so a drifting tumour stays linked,
      :func:`_largest_linked_group`), and only the linked group with the
      most tumour pixels is kept; other slices get ``selection ==
      "dropped-3d"``. A group on fewer than ``min_tumor_slices`` acquired
      slices is dropped too: on the tumour-free phantoms (seeds 0-7) one
      isolated partial-volume slice of 58-1290 px otherwise always survived
      as "the largest group". The cost: a tumour thinner than one slice step
      is not reported. Through-slice partial volume at the base and vertex
      of the brain (CSF averaged with grey matter to a tumour-like gray)
      otherwise yields isolated false tumours on end slices (measured on the
      phantoms: up to 1158 px on a slice, +5 % to +15 % of the volume). This
      assumes a single tumour; switch it off for multifocal disease.
    - Tips: the slice just beyond each end of the kept tumour is searched
      for the tumour's tip inside the end slice's mask dilated by one pixel,
      each pixel decided by partial volume between the end slice's tumour
      gray and the gray around that mask on the tip slice, a third tissue
      beyond the tumour's gray (CSF on T2) and its partial-volume ring
      excluded (``selection == "extended-3d"``; see :func:`_extend_tips`).
    """
    keep = _largest_linked_group(out.tumor, p.component_tolerance_px)
    if np.count_nonzero(keep.any(axis=(1, 2))) < p.min_tumor_slices:
        keep = np.zeros_like(out.tumor)
    dropped = np.flatnonzero(out.tumor.any(axis=(1, 2)) & ~keep.any(axis=(1, 2)))
    out.selection[dropped] = "dropped-3d"
    out.center_gray[dropped] = np.nan
    out.tumor = keep
    for z, mask, v_used in _extend_tips(out.tumor, img, brain, out.centers, p.min_tumor_pixels):
        out.tumor[z] = mask
        out.selection[z] = "extended-3d"
        out.center_gray[z] = v_used


@register_method(
    "paper",
    description="the paper's per-slice wavelet + histogram fuzzy c-means ([A7], [A8])",
    measures=(
        "the tumour cluster of the paper's per-slice wavelet + fuzzy c-means segmentation "
        "(Arakeri & Reddy 2013, section 3) on {seq}"
    ),
)
def segment_paper(
    enhanced: np.ndarray,
    brain_mask: np.ndarray,
    detection: SliceDetection,
    *,
    modality: str,
    wavelet: str,
    fuzziness: float,
    tol: float,
    max_num_iter: int,
    min_tumor_pixels: int,
    keep_largest_3d_component: bool,
    component_tolerance_px: int,
    rim_px: int,
    max_brain_fraction: float,
    refine_boundary: bool,
    min_tumor_slices: int,
    spacing_mm: tuple[float, float, float] | None,
    head_exterior: np.ndarray | None,
) -> SegmentationResult:
    """The paper's method (:func:`_segment_paper`: its steps) with the caveats of its mask.

    Parameters
    ----------
    enhanced : (z, y, x) ndarray of uint8
        ``J`` of section 1 (or another dtype holding whole gray levels 0-255).
    brain_mask : (z, y, x) ndarray of bool
        ``M_brain`` of section 1 (or 0/1 values of another dtype).
    detection : SliceDetection
        Section 2 result for the same slices (``k`` and the seeds).
    modality : {"t2", "flair", "t1c"}
        Sequence (case-insensitive), for the plausibility check and the rule.
    wavelet : {"haar"}
        Wavelet of the one-level DWT; only Haar makes ``LL/2`` the block mean.
    fuzziness, tol, max_num_iter : float, float, int
        FCM exponent ``m > 1``, stop threshold on the centre change (gray
        levels) and iteration limit.
    min_tumor_pixels : int
        Smallest tumour component kept on a slice, pixels.
    keep_largest_3d_component : bool
        Keep only the largest group of slice masks linked across slices.
    component_tolerance_px : int
        In-plane dilation radius (pixels) linking masks of consecutive slices.
    rim_px : int
        Width (pixels) of the brain rim where no tumour component is seeded (0: literal step 5).
    max_brain_fraction : float
        Largest share of a slice's brain cross-section the tumour may cover; 1 disables it.
    refine_boundary : bool
        Decide the pixels on the tumour's boundary by partial volume.
    min_tumor_slices : int
        With ``keep_largest_3d_component``, the fewest acquired slices the kept tumour spans.
    spacing_mm : (3,) tuple of float, optional
        Voxel spacing ``(slice step, row, column)`` for the mask's caveats.
    head_exterior : (z, y, x) ndarray of bool, optional
        The air outside a raw head, for the scalp caveat.

    Returns
    -------
    SegmentationResult
        With ``method="paper"`` and the caveats of its mask
        (:func:`~tumor3d.segmentation.caveats.segmentation_caveats`,
        :func:`premise_caveat`).

    Raises
    ------
    InputError
        On wrong dimensions, dtypes or shapes, a detection of another length,
        an unknown modality or wavelet, or an out-of-range parameter.
    """
    img, brain = _checked_paper_inputs(enhanced, brain_mask, detection, wavelet)
    p = _PaperParams(
        modality=modality, m=fuzziness, tol=tol, max_num_iter=max_num_iter,
        min_tumor_pixels=min_tumor_pixels, keep_largest_3d_component=keep_largest_3d_component,
        component_tolerance_px=component_tolerance_px, rim_px=rim_px,
        max_brain_fraction=max_brain_fraction, refine_boundary=refine_boundary,
        min_tumor_slices=min_tumor_slices,
    )  # fmt: skip
    res = _segment_paper(img, brain, detection, p)
    caveats = segmentation_caveats(
        res.tumor_mask, spacing_mm=spacing_mm, head_exterior=head_exterior
    )
    return replace(res, caveats=caveats + premise_caveat(detection), method="paper")


def premise_caveat(detection: SliceDetection) -> tuple[str, ...]:
    """The paper's method run where its premise does not hold, in words (or nothing).

    The method finds the tumour as the histogram mode a normal slice lacks:
    it assumes white matter, grey matter and CSF each form a mode on every
    slice (T2 at the paper's resolution; [A5], [A6]). Where fewer slices
    show them than ``segment.method: auto`` asks before choosing the method
    (:data:`tumor3d.segmentation.detect.methods.PAPER_PREMISE_FRACTION`), its
    clusters are not the tissues it names: measured on the labelled real
    cases (0.46-0.79 of their thick slices show the three modes; every
    slice of the T2 phantoms does), it finds little or nothing there
    (``reports/learned_cv.md``). The run then asks for a check.
    """
    share = paper_premise_share(detection.n_modes, detection.brain_pixels)
    if share >= PAPER_PREMISE_FRACTION:
        return ()
    return (
        "the paper's method ran outside its premise, check the outline (it may miss most of "
        f"the tumour): three tissue modes (white matter, grey matter, CSF) show on "
        f"{100.0 * share:.0f} % of the slices with brain, where it assumes nearly all "
        f"({100.0 * PAPER_PREMISE_FRACTION:.0f} %)",
    )
