"""The U-Net's input and output grids: one patient's slices in, probabilities back.

Shared by inference (:mod:`tumor3d.learned.cnn`) and training
(``benchmarks/cnn_cv.py``), so that the network is trained on exactly what it
is given. Arrays are ``(z, y, x)``: slices first, in the volume's own order.
The network sees each slice resampled to ``size`` x ``size`` (the whole slice,
so the field of view sets the scale), 2.5-D: the slice and ``context``
neighbours each side as channels (the end slices repeat). Intensity is
``(I - median) / robust SD`` over the head's tissue, per patient
(:func:`tumor3d.learned.features.normalise_intensity`, as the forest's features),
clipped to [-5, 10] and divided by 3.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from tumor3d.learned.features import normalise_intensity, tissue_foreground

__all__ = ["case_input", "case_target", "upsample"]


def case_input(image: np.ndarray, size: int, context: int) -> np.ndarray:
    """Network input ``(z, 2 context + 1, size, size)`` float16 of one volume ``(z, y, x)``.

    >>> case_input(np.random.default_rng(0).random((3, 20, 30)), 8, 1).shape
    (3, 3, 8, 8)
    """
    img = np.asarray(image, np.float32)
    norm = np.clip(normalise_intensity(img, tissue_foreground(img)), -5.0, 10.0) / 3.0
    z, h, w = norm.shape
    small = ndi.zoom(norm, (1.0, size / h, size / w), order=1, grid_mode=True, mode="nearest")
    idx = np.clip(np.arange(z)[:, None] + np.arange(-context, context + 1)[None, :], 0, z - 1)
    return small[idx].astype(np.float16)


def case_target(ref: np.ndarray, size: int) -> np.ndarray:
    """The reference ``(z, y, x)`` resampled to ``size`` x ``size`` (area fraction, float16)."""
    r = np.asarray(ref, np.float32)
    z, h, w = r.shape
    return np.clip(
        ndi.zoom(r, (1.0, size / h, size / w), order=1, grid_mode=True, mode="nearest"), 0, 1
    ).astype(np.float16)


def upsample(prob: np.ndarray, shape: tuple[int, int, int]) -> np.ndarray:
    """``(z, s, s)`` probabilities back to the native ``shape``, bilinear, in [0, 1].

    >>> upsample(np.full((2, 4, 4), 0.5, np.float32), (2, 10, 12)).shape
    (2, 10, 12)
    """
    z, h, w = shape
    s = prob.shape[1]
    out = ndi.zoom(
        prob.astype(np.float32),
        (1.0, h / s, w / prob.shape[2]),
        order=1,
        grid_mode=True,
        mode="nearest",
    )
    return np.clip(out[:, :h, :w], 0.0, 1.0)
