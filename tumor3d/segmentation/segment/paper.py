"""The paper's method: per-slice wavelet + histogram fuzzy c-means (``segment.method: paper``)."""

from __future__ import annotations

from dataclasses import replace

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
    enhanced: np.ndarray,
    brain_mask: np.ndarray,
    detection: SliceDetection,
    *,
    modality: str = "t2",
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
) -> SegmentationResult:
    """The paper's segmentation (``method="paper"``, specification section 3).

    For each slice flagged abnormal by ``detection`` with ``k`` modes:

    1. [A7] ``h_LL`` = histogram of the Haar ``LL/2`` band (the 2x2 block
       mean) over the 2x2 blocks that lie entirely in the brain mask;
    2. histogram FCM (:func:`fuzzy_cmeans_histogram`) with ``C = k``,
       ``m = fuzziness`` and the peak gray levels of section 2 as seeds;
    3. each full-resolution brain pixel of ``J`` takes the cluster of
       maximum membership of its gray level;
    4. [A8] the reference centres ``r`` (3, ascending) come from FCM with
       ``C = 3`` on the pooled ``h_LL`` of all the patient's slices that are
       *not* abnormal (seeded at the 1/6, 1/2 and 5/6 quantiles). The
       slice's centres are matched to ``r`` by the Hungarian algorithm on
       ``|v - r|``; the tumour is the unmatched cluster farthest from all
       references (or, with several unmatched, the most populous one: see
      :func:`_choose_tumor_cluster`). Without references (no normal slice) the modality rule
       applies: T2 second-brightest cluster (WM < GM < tumour < CSF),
       FLAIR and T1c brightest cluster;
    5. mask = largest 4-connected component of the tumour cluster, holes
       filled; dropped (empty slice) if smaller than ``min_tumor_pixels``.

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
    - Brain rim (``rim_px``): the tumour component of step 5 is chosen among
      cluster pixels at least ``rim_px`` inside the brain mask and then
      regains its own pixels near the rim. Where a thick slice cuts the
      brain surface obliquely, CSF and grey matter average to a
      tumour-like gray along the boundary; that rim, hole-filled, became a
      disc covering most of the brain (measured on the phantoms: 2832 of
      4141 brain pixels on a slice).
    - Brain fraction (``max_brain_fraction``): a component covering more than
      this fraction of the slice's brain is the partial volume of a slice
      cutting the brain surface nearly tangentially (at the base and the
      vertex), not a tumour; the slice gets ``selection ==
      "partial-volume"``. Measured on the phantoms: 3348 of 4701 brain
      pixels on such a slice.
    - T2 and CSF: a cluster at or above the CSF reference is pinned to CSF
      in the assignment (nothing in the brain is brighter than CSF on T2).
      The CSF reference is pulled down by partial volume of the thin CSF
      rim; unpinned, real CSF was left unmatched and taken as tumour.
    - Boundary (``refine_boundary``): FCM labels a pixel half tumour, half
      white matter as grey matter (its gray lies between the two), so the
      mask shrinks wherever the tumour borders white matter: -8 % of the
      pixels of a 27 mm phantom tumour. Pixels touching the mask are
      re-decided by partial volume (:func:`_refine_boundary`).
    - Tips: with ``keep_largest_3d_component``, the slice just beyond each
      end of the kept tumour is searched for the tumour's tip inside the end
      slice's mask dilated by one pixel, each pixel decided by partial
      volume between the end slice's tumour gray and the gray around that
      mask on the tip slice, a third tissue beyond the tumour's gray (CSF on
      T2) and its partial-volume ring excluded (``selection ==
      "extended-3d"``; see :func:`_extend_tips`).
    - 3-D consistency (``keep_largest_3d_component``): the slice masks are
      linked across consecutive slices where they overlap once each is
      dilated in-plane by ``component_tolerance_px`` (so a drifting tumour
      stays linked), and only the linked group with the most tumour pixels
      is kept; other slices get ``selection == "dropped-3d"``. A group on
      fewer than ``min_tumor_slices`` acquired slices is dropped too: on the
      tumour-free phantoms (seeds 0-7) one isolated partial-volume slice of
      58-1290 px otherwise always survived as "the largest group". The cost:
      a tumour thinner than one slice step is not reported. Through-slice
      partial volume at the base and vertex of the brain (CSF averaged with
      grey matter to a tumour-like gray) otherwise yields isolated false
      tumours on end slices (measured on the phantoms: up to 1158 px on a
      slice, +5 % to +15 % of the volume). This assumes a single tumour;
      switch it off for multifocal disease.

    The paper's configuration (``configs/paper.yaml``) keeps the literal
    step 5 (``rim_px=0``) and takes ``refine_boundary``,
    ``max_brain_fraction=0.5`` and ``keep_largest_3d_component``, each
    measured on the T2 phantoms of ``reports/PAPER.md`` (seeds 0-7, tumour-free
    0-3; ``make paper``) by reverting it alone: with pixels labelled by their
    cluster ([A8] literally) Eq. 9 is 3.2 % on average and 5.4 % per slice
    (0.80 % and 2.05 % with the boundary decided by partial volume); without
    the brain-fraction check 6 of 64 tumour slices are lost (the largest
    linked group is then an end slice's partial volume); slice by slice, 16
    of 185 normal slices keep a false tumour and 5 tumour tips are missed.
    With all three, every tumour slice and no normal slice is reported and
    Eq. 7 lies within 1.31 % of the truth.

    Parameters
    ----------
    enhanced : (z, y, x) ndarray of uint8
        ``J`` of section 1 (another dtype is accepted if it holds whole gray
        levels 0-255).
    brain_mask : (z, y, x) ndarray of bool
        ``M_brain`` of section 1 (0/1 values of another dtype are accepted).
    detection : SliceDetection
        Section 2 result for the same slices (``k`` and the seeds).
    modality : {"t2", "flair", "t1c"}
        Sequence (case-insensitive), used by the plausibility check and the
        fallback rule.
    wavelet : {"haar"}
        Wavelet of the one-level DWT; only Haar makes ``LL/2`` the block mean.
    fuzziness : float
        FCM exponent ``m > 1``.
    tol : float
        FCM stop threshold on the centre change, gray levels.
    max_num_iter : int
        FCM iteration limit.
    min_tumor_pixels : int
        Smallest tumour component kept on a slice, pixels.
    keep_largest_3d_component : bool
        Keep only the largest group of slice masks linked across slices.
    component_tolerance_px : int
        In-plane dilation radius (pixels) used to link masks of consecutive
        slices.
    rim_px : int
        Width (pixels) of the brain rim where a tumour component may not be
        seeded; 0 gives the literal step 5.
    max_brain_fraction : float
        Largest plausible share of a slice's brain cross-section covered by
        the tumour; 1 disables the check.
    refine_boundary : bool
        Decide the pixels on the tumour's boundary by partial volume (see
        :func:`_refine_boundary`).
    min_tumor_slices : int
        With ``keep_largest_3d_component``, the fewest acquired slices the
        kept tumour must span.

    Returns
    -------
    SegmentationResult

    Raises
    ------
    InputError
        On wrong dimensions, dtypes or shapes, a detection of another length,
        an unknown modality or wavelet, or an out-of-range parameter.
    """
    img, brain = _check_pair(enhanced, brain_mask)
    if not isinstance(detection, SliceDetection):
        raise InputError("detection must be a SliceDetection")
    if len(detection) != img.shape[0]:
        raise InputError(f"detection has {len(detection)} slices but enhanced has {img.shape[0]}")
    mod = modality.strip().lower() if isinstance(modality, str) else modality
    if mod not in MODALITIES:
        raise InputError(f"unknown modality {modality!r}: expected one of {MODALITIES}")
    if wavelet != "haar":
        raise InputError(f"unsupported wavelet {wavelet!r}: only 'haar' is implemented")
    _check_fcm_params(fuzziness, tol, max_num_iter)
    if int(min_tumor_pixels) < 1:
        raise InputError(f"min_tumor_pixels must be >= 1, got {min_tumor_pixels}")
    if int(min_tumor_slices) < 1:
        raise InputError(f"min_tumor_slices must be >= 1, got {min_tumor_slices}")
    if not 0.0 < float(max_brain_fraction) <= 1.0:
        raise InputError(f"max_brain_fraction must lie in (0, 1], got {max_brain_fraction}")
    if int(rim_px) < 0:
        raise InputError(f"rim_px must be >= 0, got {rim_px}")
    if int(component_tolerance_px) < 0:
        raise InputError(f"component_tolerance_px must be >= 0, got {component_tolerance_px}")
    m, tol, max_num_iter = float(fuzziness), float(tol), int(max_num_iter)

    nz = img.shape[0]
    hists = _ll_histograms(img, brain)
    normal = ~detection.abnormal
    ref = _reference_centers(hists[normal].sum(axis=0), m, tol, max_num_iter)

    tumor = np.zeros(img.shape, dtype=bool)
    center_gray = np.full(nz, np.nan)
    selection = np.full(nz, "", dtype=object)
    gray = np.arange(N_GRAY, dtype=np.float64)
    centers: dict[int, tuple[np.ndarray, int]] = {}
    fcm_iter = np.full(nz, -1, dtype=np.int64)
    fcm_conv = np.zeros(nz, dtype=bool)
    for z in np.flatnonzero(detection.abnormal):
        seeds = detection.peaks_gray[z]
        if seeds.size == 0 or not hists[z].sum() > 0:
            selection[z] = "none"
            continue
        v, diag = _fcm_histogram(hists[z], seeds, m, tol, max_num_iter)
        fcm_iter[z] = diag.n_iter
        fcm_conv[z] = diag.converged
        label_of_gray = np.argmax(fcm_memberships(gray, v, m), axis=0)
        pixel_hist = np.bincount(img[z][brain[z]], minlength=N_GRAY)
        mass = np.bincount(label_of_gray, weights=pixel_hist, minlength=v.size)
        t, how = _choose_tumor_cluster(v, ref, mod, mass)
        selection[z] = how
        if t < 0:
            continue
        centers[z] = (v, t)
        cluster = brain[z] & (label_of_gray[img[z]] == t)
        mask = _tumor_component(cluster, brain[z], int(rim_px))
        if refine_boundary and mask.any():
            mask = _refine_boundary(mask, img[z], brain[z], float(v[t]))
        if mask.sum() < int(min_tumor_pixels):
            selection[z] = "none"
            continue
        if mask.sum() > float(max_brain_fraction) * brain[z].sum():
            selection[z] = "partial-volume"
            continue
        tumor[z] = mask
        center_gray[z] = v[t]
    if keep_largest_3d_component:
        keep = _largest_linked_group(tumor, int(component_tolerance_px))
        if np.count_nonzero(keep.any(axis=(1, 2))) < int(min_tumor_slices):
            keep = np.zeros_like(tumor)
        dropped = np.flatnonzero(tumor.any(axis=(1, 2)) & ~keep.any(axis=(1, 2)))
        selection[dropped] = "dropped-3d"
        center_gray[dropped] = np.nan
        tumor = keep
        for z, mask, v_used in _extend_tips(tumor, img, brain, centers, int(min_tumor_pixels)):
            tumor[z] = mask
            selection[z] = "extended-3d"
            center_gray[z] = v_used
    return SegmentationResult(
        tumor_mask=tumor,
        tumor_pixels=tumor.sum(axis=(1, 2)).astype(np.int64),
        reference_centers=ref,
        tumor_center_gray=center_gray,
        selection=np.array(selection.tolist(), dtype=str),
        fcm_iterations=fcm_iter,
        fcm_converged=fcm_conv,
    )


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
    """The paper's method (:func:`_segment_paper`) with the caveats of its mask."""
    res = _segment_paper(
        enhanced,
        brain_mask,
        detection,
        modality=modality,
        wavelet=wavelet,
        fuzziness=fuzziness,
        tol=tol,
        max_num_iter=max_num_iter,
        min_tumor_pixels=min_tumor_pixels,
        keep_largest_3d_component=keep_largest_3d_component,
        component_tolerance_px=component_tolerance_px,
        rim_px=rim_px,
        max_brain_fraction=max_brain_fraction,
        refine_boundary=refine_boundary,
        min_tumor_slices=min_tumor_slices,
    )
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
