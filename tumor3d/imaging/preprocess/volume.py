"""The preprocessing of a stack, steps 1-4 in order: :func:`preprocess_volume`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tumor3d.errors import InputError
from tumor3d.imaging.brain_extraction import extract_brain, head_around_brain, head_exterior
from tumor3d.imaging.preprocess.filters import (
    _median_stack,
    _unsharp_stack,
    equalize_slices,
)
from tumor3d.imaging.preprocess.intensity import (
    _check_percentiles,
    _check_volume,
    _to_uint8,
    masked_background,
)
from tumor3d.imaging.preprocess.masks import _foreground_brain_mask
from tumor3d.imaging.preprocess.skull import remove_skull


@dataclass(frozen=True, eq=False)
class PreprocessResult:
    """Output of :func:`preprocess_volume`; all arrays are ``(z, y, x)``.

    Attributes
    ----------
    original_u8 : ndarray of uint8
        ``I``: the 8-bit slices the method starts from.
    enhanced : ndarray of uint8
        ``J = I3 * M_brain``: median filtered (and, if enabled, sharpened and
        equalised), with everything outside the brain set to 0.
    brain_mask : ndarray of bool
        ``M_brain``: the brain after skull removal (empty on slices without
        tissue).
    brain_extraction : str
        How ``M_brain`` was found: ``"given"`` (``brain_mask``),
        ``"foreground"``, ``"skull_strip"`` or ``"head"`` (the
        ``brain_extraction`` used, ``auto`` resolved).
    head_exterior : ndarray of bool or None
        Where the brain was found inside a raw head (``"skull_strip"``,
        ``"head"``) and the volume shows a head around it
        (:func:`tumor3d.imaging.brain_extraction.head_around_brain`): the air outside
        the head (:func:`tumor3d.imaging.brain_extraction.head_exterior`), which no
        brain voxel comes within the scalp and skull's thickness of. None for a
        skull-stripped volume (``"foreground"``), a given mask, and a volume
        of the brain alone.
    """

    original_u8: np.ndarray
    enhanced: np.ndarray
    brain_mask: np.ndarray
    brain_extraction: str = ""
    head_exterior: np.ndarray | None = None


BRAIN_EXTRACTIONS = ("auto", "skull_strip", "foreground", "head")


def preprocess_volume(
    image: np.ndarray,
    *,
    window_percentiles=(0.5, 99.5),
    median_size: int = 3,
    sharpen: bool = False,
    unsharp_alpha: float = 0.2,
    equalize: bool = False,
    equalize_levels: int = 256,
    skull_threshold: str = "multiotsu",
    skull_opening_radius: int = 2,
    brain_extraction: str = "auto",
    masked_background_fraction: float = 0.3,
    brain_mask: np.ndarray | None = None,
    spacing_mm: tuple[float, float, float] | None = None,
) -> PreprocessResult:
    """Run section 1 of the specification on a stack of slices.

    ``I`` is ``image`` itself when it is already uint8 (the paper's 8-bit
    slices are used as they are), otherwise :func:`to_uint8` of it. Then

    - ``I1 = median(I)``, ``median_size`` x ``median_size``, zero padding
      (MATLAB ``medfilt2``), as a ``(1, s, s)`` filter over the stack;
    - ``I2 = clip(round(I1 (*) h), 0, 255)``, ``h`` = :func:`unsharp_kernel`
      of ``unsharp_alpha`` [A1], zero padding (MATLAB ``imfilter``), if
      ``sharpen``; otherwise ``I2 = I1``;
    - ``I3`` = :func:`equalize_slices` of ``I2`` with ``equalize_levels``
      levels [A2], if ``equalize``; otherwise ``I3 = I2``;
    - ``M_brain`` = :func:`remove_skull` of ``I`` [A3], or the image's own
      foreground when it is already skull-stripped (``brain_extraction``,
      see :func:`foreground_brain_mask`), or ``brain_mask`` when given;
    - ``J = I3 * M_brain``.

    Why ``sharpen`` and ``equalize`` are off by default and in
    ``configs/paper.yaml`` (deviation from the paper's steps 2-3, measured on
    the T2 phantoms seeds 0-7 and tumour-free 0-3 of ``reports/PAPER.md``):

    - Histogram equalisation maps each gray level to its cumulative
      frequency ``T = cdf``, so the equalised histogram is flat by
      construction (output density ``p / T' = 1``): its modes, which
      section 2 counts and section 3 clusters, are spread into a uniform
      band. Over the whole slice (the literal reading [A2]) the air and
      scalp take most of the levels and the brain is squeezed into 180-255
      (demo phantom, slice 15: WM 206, GM 230, tumour 242, CSF 255); the FCM
      then finds no tumour cluster on any slice (the paper configuration
      with ``equalize=True``, 256 or 64 levels: 0 of 64 tumour slices
      segmented). No reading restores the modes: brain only, whole volume,
      256 or 64 levels, before or after sharpening, Otsu or multi-Otsu skull
      mask, the full-resolution or the Haar ``LL`` histogram: at best 42 of
      64 tumour slices flagged with 4 normal slices flagged, or all 64 with
      125 or more of 185 normal slices flagged.
    - The unsharp kernel (centre weight ``(alpha+5)/(alpha+1) = 4.33``)
      amplifies noise about 4.5-fold and creates over/undershoots at every
      tissue edge, clipped into spikes at 0 and 255; these become extra
      histogram modes. At a bright tumour's edge the overshoot saturates at
      255, the gray of CSF on T2, and the FCM labels the tumour's inner rim
      CSF (demo slice 15: 103 of 972 tumour pixels lost, grays 190-255): the
      paper configuration with ``sharpen=True`` loses 10 % of the tumour
      pixels on average (Eq. 9), 14 % at worst.

    Both steps remain available (``sharpen=True, equalize=True`` is the
    paper's literal chain).

    Parameters
    ----------
    image : (z, y, x) ndarray of real numbers
        The slices, ``z`` the slice axis. Not modified.
    window_percentiles : (float, float)
        Foreground percentiles of the 8-bit window (ignored for uint8 input).
    median_size : int
        Odd median filter size in pixels.
    sharpen : bool
        Apply the unsharp kernel (paper step 2).
    unsharp_alpha : float
        ``alpha`` of ``fspecial('unsharp')``, in ``[0, 1]``.
    equalize : bool
        Apply per-slice histogram equalisation (paper step 3).
    equalize_levels : int
        Gray levels of the equalised image, 2-256.
    skull_threshold : {"multiotsu", "otsu"}
        Threshold of the skull removal, see :func:`remove_skull`.
    skull_opening_radius : int
        Radius (pixels) of the disk of the skull removal's opening.
    brain_extraction : {"auto", "skull_strip", "foreground", "head"}
        ``skull_strip``: :func:`remove_skull` (the paper's step 4);
        ``foreground``: :func:`foreground_brain_mask` (the volume is already
        skull-stripped: keep the whole brain, no rim eaten); ``head``:
        :func:`tumor3d.imaging.brain_extraction.extract_brain`, a 3-D extraction in mm
        for raw clinical heads where the per-slice skull removal keeps the
        scalp (measured on the raw heads of ``../shared/data``: 1.2-1.5 L
        brains instead of 2.6-3.3 L heads; not the default, because on the
        phantoms, where the skull removal succeeds, it loses the end slices
        and a 1-2 mm rim, and because the lesion model then reported false
        lesions in normal white matter on two raw T1 heads, see
        ``reports/segmentation.md``; needs ``spacing_mm``); ``auto``:
        ``foreground`` when at least ``masked_background_fraction`` of the
        voxels hold the masked background value (:func:`masked_background`:
        the volume's minimum or the border's most frequent value, up to the
        rounding of a resampling), else ``skull_strip``.
        Reason: the air of a raw magnitude MR volume carries Rician noise,
        so a large set of voxels sharing one exact value is a mask applied
        by skull stripping (0 in BraTS T2, the z-scored background -3.16 of
        the BraTS FLAIR cases). Measured: 81-89 % on the BraTS volumes,
        2-6 % on the raw clinical volumes of ``../shared/data``.
    masked_background_fraction : float
        Threshold of the ``auto`` rule, in (0, 1].
    brain_mask : (z, y, x) array_like of bool, optional
        A known brain mask (e.g. BraTS ``brainmask``); replaces the skull
        removal. Not a configuration parameter.
    spacing_mm : (3,) tuple of float, optional
        Voxel spacing ``(slice step, row, column)`` in mm; needed by
        ``brain_extraction="head"``. Not a configuration parameter (the stage
        adapter passes the scan's).

    Returns
    -------
    PreprocessResult

    Raises
    ------
    InputError
        For a non-3-D, non-real, NaN-containing or constant ``image``, a
        ``brain_mask`` of another shape, or an out-of-range parameter.

    References
    ----------
    R. Arakeri, G. R. M. Reddy, "3D reconstruction of brain tumor and volume
    estimation from MR images", IJSIP 6(3), 2013, section 3.1.
    """
    arr = _check_volume(image)
    lo_p, hi_p = _check_percentiles(window_percentiles)
    size = int(median_size)
    if size < 1 or size % 2 == 0:
        raise InputError(f"median_size must be a positive odd integer, got {median_size}")
    if not 0.0 <= float(unsharp_alpha) <= 1.0:
        raise InputError(f"unsharp_alpha must lie in [0, 1], got {unsharp_alpha}")
    if not 2 <= int(equalize_levels) <= 256:
        raise InputError(f"equalize_levels must lie in [2, 256], got {equalize_levels}")
    if brain_mask is not None:
        given = np.asarray(brain_mask)
        if given.shape != arr.shape:
            raise InputError(
                f"brain_mask shape {given.shape} does not match image shape {arr.shape}"
            )
        given = given.astype(bool)
    if arr.dtype == np.uint8:
        if arr.min() == arr.max():
            raise InputError("image is constant: there is no tissue to process")
        original = arr.copy()
        background = None
    else:
        background = masked_background(arr)  # computed once: the window, auto, foreground
        original = _to_uint8(arr, lo_p, hi_p, background)
    enhanced = _median_stack(original, size)
    if sharpen:
        enhanced = _unsharp_stack(enhanced, unsharp_alpha)
    if equalize:
        enhanced = equalize_slices(enhanced, levels=equalize_levels)
    if brain_extraction not in BRAIN_EXTRACTIONS:
        raise InputError(
            f"unknown brain_extraction {brain_extraction!r}: expected one of {BRAIN_EXTRACTIONS}"
        )
    if not 0.0 < float(masked_background_fraction) <= 1.0:
        raise InputError(
            f"masked_background_fraction must lie in (0, 1], got {masked_background_fraction}"
        )
    mode = brain_extraction
    if mode == "auto":
        share = (masked_background(arr) if background is None else background).share
        mode = "foreground" if share >= float(masked_background_fraction) else "skull_strip"
    if spacing_mm is not None:
        sp = tuple(float(v) for v in np.ravel(spacing_mm))
        if len(sp) != 3 or not all(np.isfinite(v) and v > 0 for v in sp):
            raise InputError(f"spacing_mm must be three positive numbers, got {spacing_mm}")
    if brain_mask is not None:
        brain = given
        mode = "given"
    elif mode == "foreground":
        brain = _foreground_brain_mask(arr, background)
    elif mode == "head":
        if spacing_mm is None:
            raise InputError("brain_extraction 'head' needs the voxel spacing (spacing_mm)")
        brain = extract_brain(original, sp)
    else:
        brain = remove_skull(
            original, opening_radius=skull_opening_radius, threshold=skull_threshold
        )

    enhanced = np.where(brain, enhanced, np.uint8(0))
    exterior = None
    if mode in ("skull_strip", "head"):  # a raw head: its air, if it shows a head at all
        pixel_mm = (1.0, 1.0) if spacing_mm is None else (sp[1], sp[2])
        exterior = head_exterior(original, pixel_mm)
        if not head_around_brain(brain, exterior, pixel_mm):
            exterior = None
    return PreprocessResult(
        original_u8=original, enhanced=enhanced, brain_mask=brain, brain_extraction=mode,
        head_exterior=exterior,
    )  # fmt: skip
