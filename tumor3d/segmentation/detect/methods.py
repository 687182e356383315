"""The detection methods and the paper's premise, which ``auto`` checks to choose one."""

from __future__ import annotations

import numpy as np

DETECT_METHODS = ("auto", "robust", "histogram")

#: The paper's premise ([A5], [A6]): a normal slice shows three tissue modes (WM, GM,
#: CSF on T2). On T2, ``auto`` takes the paper's method only where the premise holds on
#: (nearly) every slice of the patient: at least this share of the slices with
#: ``PREMISE_MIN_BRAIN_PIXELS`` brain pixels has >= 3 modes. Measured: every slice of
#: the T2 phantoms (1.00), 0.46-0.79 of the real BraTS thick slices.
PAPER_PREMISE_FRACTION = 0.95
PREMISE_MIN_BRAIN_PIXELS = 500


def paper_premise_share(n_modes: np.ndarray, brain_pixels: np.ndarray) -> float:
    """The share of the slices with brain that show at least three tissue modes.

    Parameters
    ----------
    n_modes, brain_pixels : (z,) array_like of int
        ``SliceDetection.n_modes`` and ``.brain_pixels``; a slice counts when it
        has at least ``PREMISE_MIN_BRAIN_PIXELS`` brain pixels.

    Returns
    -------
    float
        In [0, 1]; 0 when no slice has that much brain.

    Examples
    --------
    >>> paper_premise_share([3, 4, 2, 0], [900, 900, 900, 10])
    0.6666666666666666
    """
    k = np.asarray(n_modes)
    ok = np.asarray(brain_pixels) >= PREMISE_MIN_BRAIN_PIXELS
    return float(np.mean(k[ok] >= 3)) if ok.any() else 0.0


def paper_premise_holds(n_modes: np.ndarray, brain_pixels: np.ndarray) -> bool:
    """Whether the slices show the three tissue modes the paper's method assumes.

    Parameters
    ----------
    n_modes, brain_pixels : (z,) array_like of int
        ``SliceDetection.n_modes`` and ``.brain_pixels``.
    """
    return paper_premise_share(n_modes, brain_pixels) >= PAPER_PREMISE_FRACTION
