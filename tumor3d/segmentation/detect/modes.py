"""Mode counting: the peaks and valleys of a slice's smoothed gray-level histogram (Eq. 1)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from tumor3d.errors import InputError
from tumor3d.segmentation.detect.result import HistogramModes


def _check_mode_params(
    n_bins: int,
    smoothing_sigma_bins: float,
    min_mode_area: float,
    min_peak_distance_bins: float,
    min_valley_significance: float,
) -> None:
    if not 2 <= int(n_bins) <= 256:
        raise InputError(f"n_bins must lie in [2, 256], got {n_bins}")
    if not smoothing_sigma_bins >= 0:
        raise InputError(f"smoothing_sigma_bins must be >= 0, got {smoothing_sigma_bins}")
    if not 0 <= min_mode_area < 1:
        raise InputError(f"min_mode_area must lie in [0, 1), got {min_mode_area}")
    if not min_peak_distance_bins >= 0:
        raise InputError(f"min_peak_distance_bins must be >= 0, got {min_peak_distance_bins}")
    if not min_valley_significance >= 0:
        raise InputError(f"min_valley_significance must be >= 0, got {min_valley_significance}")


def count_histogram_modes(
    values: np.ndarray,
    *,
    n_bins: int = 64,
    smoothing_sigma_bins: float = 1.0,
    min_mode_area: float = 0.005,
    min_peak_distance_bins: float = 3,
    min_valley_significance: float = 3.0,
) -> HistogramModes:
    """Count the modes of the gray-level histogram of ``values`` ([A5]).

    1. ``h`` = histogram of ``values`` in ``n_bins`` equal bins over the gray
       levels 0-255, smoothed with a Gaussian of ``smoothing_sigma_bins``
       bins (zero outside the range).
    2. Peaks are local maxima of ``h``; a plateau counts once, at its centre.
       The valley between two adjacent peaks is the minimum of ``h``
       between them (the centre of a flat minimum).
    3. The area of a mode is the mass of ``h`` between its valleys divided
       by the total mass (a valley bin is shared half and half).
    4. Repeatedly merge, into the neighbour across the shallower (higher)
       valley, the mode of smallest area while it is below
       ``min_mode_area``; then the closest pair of peaks while they are less
       than ``min_peak_distance_bins`` apart; then (addition to [A5]) the
       pair whose valley is least significant while
       ``(min(h_peak_l, h_peak_r) - h_valley) / (c sqrt(min(h_peak_l,
       h_peak_r))) < min_valley_significance``, where ``c sqrt(n)`` is the
       standard deviation of a smoothed bin of Poisson counts with
       expectation ``n`` (``c^2`` = sum of the squared smoothing weights).
       The merged mode keeps the higher peak and the summed area.
    5. ``k`` = the number of modes; the seeds are the peak gray levels.

    The significance test makes the count independent of how many pixels
    the slice has: with only area and distance rules, the noise bumps of a
    sparse histogram tail (a few counts per bin) pass as modes, and normal
    real slices reach ``k = 5-9`` (violating [A5] step 6, "every normal
    slice gives k <= 3"); with a 3-sigma test all the normal slices of the
    real volumes we tried give ``k <= 3``. It is the tuning [A5] step 6 asks
    for, so ``configs/paper.yaml`` keeps it: without it every one of the 185
    normal slices of the T2 phantoms of ``reports/PAPER.md`` is flagged
    (``k = 4-7``) and 7 keep a false tumour; with it 35 are flagged, all at
    the brain's ends, where a 2 mm slice cut tangentially through the cortex
    averages grey matter and CSF to the tumour's gray (a genuine fourth
    mode, rejected by section 3).

    Parameters
    ----------
    values : ndarray of uint8 (any shape)
        Gray levels, typically the brain pixels of one slice of ``J``.
    n_bins : int
        Number of histogram bins over 0-255 (64 gives 4 gray levels per bin).
    smoothing_sigma_bins : float
        Gaussian smoothing, in bins; 0 disables it.
    min_mode_area : float
        Smallest mode area kept, as a fraction of the total mass.
    min_peak_distance_bins : float
        Peaks closer than this (in bins) are merged.
    min_valley_significance : float
        Valleys shallower than this many noise standard deviations are
        merged; 0 disables the test (the plain [A5] recipe).

    Returns
    -------
    HistogramModes
        Zero modes when ``values`` is empty.

    Raises
    ------
    InputError
        If ``values`` is not integer-valued within 0-255 or a parameter is
        out of range.

    References
    ----------
    J. A. Castro et al., "A new approach for automatic brain tissue
    classification by histogram analysis", 2007 (mode area and distance
    rules); Arakeri & Reddy 2013, Eq. 1.
    """
    vals = np.asarray(values)
    if not (np.issubdtype(vals.dtype, np.integer) or vals.dtype == bool):
        raise InputError(f"values must be integer gray levels (uint8), got dtype {vals.dtype}")
    if vals.size and (vals.min() < 0 or vals.max() > 255):
        raise InputError("values must be gray levels in 0-255")
    _check_mode_params(
        n_bins, smoothing_sigma_bins, min_mode_area, min_peak_distance_bins, min_valley_significance
    )
    counts = np.bincount(vals.reshape(-1).astype(np.intp), minlength=256)[:256]
    return _modes_from_counts(
        counts,
        n_bins=int(n_bins),
        sigma=float(smoothing_sigma_bins),
        min_area=float(min_mode_area),
        min_distance=float(min_peak_distance_bins),
        min_significance=float(min_valley_significance),
    )


def _bin_histogram(counts256: np.ndarray, n_bins: int) -> np.ndarray:
    """Rebin a 256-level histogram into ``n_bins`` equal bins of [0, 256)."""
    bin_of_level = (np.arange(256) * n_bins) // 256
    return np.bincount(bin_of_level, weights=counts256, minlength=n_bins).astype(np.float64)


def _bins_to_gray(position: np.ndarray, n_bins: int) -> np.ndarray:
    """Bin index (possibly fractional) -> gray level of the bin centre."""
    width = 256.0 / n_bins
    return (np.asarray(position, dtype=np.float64) + 0.5) * width - 0.5


def _find_peaks_valleys(h: np.ndarray) -> tuple[list[float], list[float], list[float]]:
    """Peaks (plateau centres) and the valley between each adjacent pair."""
    # run-length encode so that plateaus are single runs
    change = np.flatnonzero(np.diff(h) != 0) + 1
    starts = np.concatenate([[0], change])
    ends = np.concatenate([change, [h.size]]) - 1
    vals = h[starts]
    left = np.concatenate([[-np.inf], vals[:-1]])
    right = np.concatenate([vals[1:], [-np.inf]])
    is_peak = (vals > left) & (vals > right) & (vals > 0)
    peak_runs = np.flatnonzero(is_peak)
    peaks = [(starts[r] + ends[r]) / 2.0 for r in peak_runs]
    valleys: list[float] = []
    valley_heights: list[float] = []
    for a, b in zip(peak_runs[:-1], peak_runs[1:], strict=True):
        between = np.arange(a + 1, b)  # runs strictly between the two peak runs
        r = between[np.argmin(vals[between])]
        valleys.append((starts[r] + ends[r]) / 2.0)
        valley_heights.append(float(vals[r]))
    return peaks, valleys, valley_heights


def _areas(h: np.ndarray, valleys: list[float]) -> np.ndarray:
    """Mass between consecutive valleys; a valley at a bin centre is split half-half."""
    cum = np.concatenate([[0.0], np.cumsum(h)])  # cum[i] = mass of bins < i

    def mass_below(pos: float) -> float:
        # mass left of position pos: half of the bin when pos is its centre,
        # all of it when pos lies between bins i and i + 1 (centre of an even plateau)
        i = int(np.floor(pos))
        return cum[i] + h[i] * (0.5 + (pos - i))

    cuts = [0.0] + [mass_below(v) for v in valleys] + [cum[-1]]
    return np.diff(np.array(cuts))


def _gauss_weights(sigma: float) -> np.ndarray:
    if sigma <= 0:
        return np.ones(1)
    impulse = np.zeros(2 * int(4 * sigma + 1) + 1)
    impulse[impulse.size // 2] = 1.0
    return ndi.gaussian_filter1d(impulse, sigma, mode="constant", truncate=4.0)


def _modes_from_counts(
    counts256: np.ndarray,
    *,
    n_bins: int,
    sigma: float,
    min_area: float,
    min_distance: float,
    min_significance: float,
) -> HistogramModes:
    h = _bin_histogram(counts256, n_bins)
    if sigma > 0:
        h = ndi.gaussian_filter1d(h, sigma, mode="constant", cval=0.0, truncate=4.0)
    total = h.sum()
    if total <= 0:
        empty = np.zeros(0)
        return HistogramModes(0, empty, empty.copy())
    # std of a smoothed bin of Poisson counts = noise_factor * sqrt(expected count)
    noise_factor = float(np.sqrt(np.sum(_gauss_weights(sigma) ** 2)))
    peaks, valleys, valley_heights = _find_peaks_valleys(h)
    areas = list(_areas(h, valleys) / total)
    heights = [float(h[int(round(p))]) for p in peaks]

    def merge(j: int) -> None:
        """Merge mode j and mode j + 1 (across valley j)."""
        keep = j if heights[j] >= heights[j + 1] else j + 1
        peaks[j : j + 2] = [peaks[keep]]
        heights[j : j + 2] = [heights[keep]]
        areas[j : j + 2] = [areas[j] + areas[j + 1]]
        del valleys[j], valley_heights[j]

    while len(peaks) > 1:
        j_small = int(np.argmin(areas))
        if areas[j_small] < min_area:
            # neighbour across the shallower (higher) valley
            left_h = valley_heights[j_small - 1] if j_small > 0 else -np.inf
            right_h = valley_heights[j_small] if j_small < len(valleys) else -np.inf
            merge(j_small - 1 if left_h > right_h else j_small)
            continue
        gaps = np.diff(peaks)
        j_close = int(np.argmin(gaps))
        if gaps[j_close] < min_distance:
            merge(j_close)
            continue
        if min_significance > 0:
            lower = np.minimum(heights[:-1], heights[1:])
            signif = (lower - np.array(valley_heights)) / (noise_factor * np.sqrt(lower))
            j_flat = int(np.argmin(signif))
            if signif[j_flat] < min_significance:
                merge(j_flat)
                continue
        break
    return HistogramModes(
        n_modes=len(peaks),
        peaks_gray=_bins_to_gray(np.array(peaks), n_bins),
        areas=np.array(areas, dtype=np.float64),
    )
