"""The U-Net's input and output grids: one patient's slices in, probabilities back.

Shared by inference (:mod:`tumor3d.learned.cnn`) and training
(``benchmarks/cnn_cv.py``), so that the network is trained on exactly what it
is given. Arrays are ``(z, y, x)``: slices first, in the volume's own order.
The network sees each slice resampled to ``size`` x ``size``, 2.5-D: the slice
and ``context`` neighbours each side as channels (the end slices repeat). What
of the slice it sees is its *framing* (:data:`FRAMINGS`): ``"slice"``, the whole
slice, so the field of view sets the scale (the nets shipped before 2026-12-07, and
a weights file that names no framing); ``"head"``, a square around the volume's
tissue; or ``"mm"``, a square of :data:`FRAME_MM` millimetres centred on the tissue
(:func:`frame_of`; the shipped nets). With the last two the
same head stored with more or less air around it, or cropped to it, gives the
net the same pixels as long as the volume's tissue mask
(:func:`tumor3d.learned.features.tissue_foreground`) is the same: air at the
image's lowest value does not move it, but noisy air (half the clinical heads of
``../shared/data``) moves its Otsu level, so cropping such a head can move the
window and the intensity normalisation a little (``benchmarks/fov_end_to_end.py``).
Intensity is
``(I - median) / robust SD`` over the head's tissue, per patient
(:func:`tumor3d.learned.features.normalise_intensity`, as the forest's features),
clipped to [-5, 10] and divided by 3.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from tumor3d.imaging.preprocess import true_box
from tumor3d.learned.features import normalise_intensity, tissue_foreground

__all__ = ["FRAMINGS", "Frame", "case_input", "case_target", "frame_of", "upsample"]


#: What of each slice the net sees: the whole slice, a square around the head's tissue,
#: or a square of FRAME_MM millimetres centred on it.
FRAMINGS = ("slice", "head", "mm")
#: The margin of a ``"head"`` frame: the tissue's extent plus this fraction each side.
HEAD_MARGIN = 0.08
#: The side of an ``"mm"`` frame: the BraTS volumes' field of view (240 x 240 pixels of
#: 1 mm), at which the whole-slice nets shipped before learned them.
FRAME_MM = 240.0

#: A window of the slices, ``(y0, x0, rows, columns)`` in native pixels; it may reach
#: beyond the image, where it holds the image's lowest value (its air).
Frame = tuple[int, int, int, int]


def frame_of(
    image: np.ndarray, framing: str, pixel_mm: tuple[float, float] | None = None
) -> Frame | None:
    """The window of the slices ``(z, y, x)`` the net sees; None: the whole slice.

    Both other framings centre the window on the bounding box of the volume's
    tissue (:func:`tumor3d.learned.features.tissue_foreground`, every slice's
    together; the whole slice when none is found). ``"head"``: a square of the
    box's longer extent plus :data:`HEAD_MARGIN` each side. ``"mm"``:
    :data:`FRAME_MM` millimetres each way at ``pixel_mm`` (row, column spacing).

    >>> img = np.zeros((2, 40, 60), np.float32); img[:, 10:30, 20:30] = 100.0
    >>> frame_of(img, "head")
    (8, 13, 24, 24)
    >>> frame_of(img, "mm", pixel_mm=(8.0, 6.0))
    (5, 5, 30, 40)
    >>> frame_of(img, "slice") is None
    True
    """
    if framing not in FRAMINGS:
        raise ValueError(f"unknown framing {framing!r}: expected one of {', '.join(FRAMINGS)}")
    if framing == "slice":
        return None
    if framing == "mm" and pixel_mm is None:
        raise ValueError("the 'mm' framing needs the pixel spacing (pixel_mm)")
    box = true_box(tissue_foreground(np.asarray(image, np.float32)))
    if box is None:
        return None
    _, ys, xs = box
    if framing == "head":
        extent = max(ys.stop - ys.start, xs.stop - xs.start)
        rows = cols = int(np.ceil(extent * (1.0 + 2.0 * HEAD_MARGIN)))
    else:
        rows, cols = (max(1, int(round(FRAME_MM / float(mm)))) for mm in pixel_mm)
    y0 = int(np.floor((ys.start + ys.stop - rows) / 2.0))
    x0 = int(np.floor((xs.start + xs.stop - cols) / 2.0))
    return y0, x0, rows, cols


def _overlap(frame: Frame, h: int, w: int) -> tuple[tuple[slice, ...], tuple[slice, ...]] | None:
    """The pixels a ``frame`` shares with an ``h`` x ``w`` slice; None if it shares none.

    Returns the image's index and the frame's, each ``(:, rows, columns)``.
    """
    y0, x0, rows, cols = frame
    sy, sx = max(0, y0), max(0, x0)
    ey, ex = min(h, y0 + rows), min(w, x0 + cols)
    if sy >= ey or sx >= ex:
        return None
    image = (slice(None), slice(sy, ey), slice(sx, ex))
    return image, (slice(None), slice(sy - y0, ey - y0), slice(sx - x0, ex - x0))


def _window(vol: np.ndarray, frame: Frame | None, fill: float) -> np.ndarray:
    """The ``frame`` of every slice of ``vol`` ``(z, y, x)``, ``fill`` beyond the image."""
    if frame is None:
        return vol
    out = np.full((vol.shape[0], frame[2], frame[3]), fill, vol.dtype)
    shared = _overlap(frame, *vol.shape[1:])
    if shared is not None:
        out[shared[1]] = vol[shared[0]]
    return out


def case_input(
    image: np.ndarray, size: int, context: int, frame: Frame | None = None
) -> np.ndarray:
    """Network input ``(z, 2 context + 1, size, size)`` float16 of one volume ``(z, y, x)``.

    ``frame``: the window the net sees (:func:`frame_of`); None, the whole slice.

    >>> case_input(np.random.default_rng(0).random((3, 20, 30)), 8, 1).shape
    (3, 3, 8, 8)
    """
    img = np.asarray(image, np.float32)
    img = _window(img, frame, float(img.min()) if img.size else 0.0)
    norm = np.clip(normalise_intensity(img, tissue_foreground(img)), -5.0, 10.0) / 3.0
    z, h, w = norm.shape
    small = ndi.zoom(norm, (1.0, size / h, size / w), order=1, grid_mode=True, mode="nearest")
    idx = np.clip(np.arange(z)[:, None] + np.arange(-context, context + 1)[None, :], 0, z - 1)
    return small[idx].astype(np.float16)


def case_target(ref: np.ndarray, size: int, frame: Frame | None = None) -> np.ndarray:
    """The reference ``(z, y, x)`` in ``frame``, resampled to ``size`` x ``size``.

    Each pixel is its area fraction of tumour, float16.
    """
    r = _window(np.asarray(ref, np.float32), frame, 0.0)
    z, h, w = r.shape
    return np.clip(
        ndi.zoom(r, (1.0, size / h, size / w), order=1, grid_mode=True, mode="nearest"), 0, 1
    ).astype(np.float16)


def upsample(
    prob: np.ndarray, shape: tuple[int, int, int], frame: Frame | None = None
) -> np.ndarray:
    """``(z, s, s)`` probabilities back to the native ``shape``, bilinear, in [0, 1].

    ``frame``: the window they cover (:func:`frame_of`); 0 outside it. None:
    the whole slice.

    >>> upsample(np.full((2, 4, 4), 0.5, np.float32), (2, 10, 12)).shape
    (2, 10, 12)
    >>> p = upsample(np.ones((1, 4, 4), np.float32), (1, 10, 12), frame=(-2, 6, 8, 8))
    >>> p.shape, int(p.sum()), bool(p[0, :6, 6:].all())
    ((1, 10, 12), 36, True)
    """
    z, h, w = shape
    if frame is None:
        th, tw = h, w
    else:
        th, tw = frame[2], frame[3]
    out = ndi.zoom(
        prob.astype(np.float32),
        (1.0, th / prob.shape[1], tw / prob.shape[2]),
        order=1,
        grid_mode=True,
        mode="nearest",
    )
    out = np.clip(out[:, :th, :tw], 0.0, 1.0)
    if frame is None:
        return out
    full = np.zeros((z, h, w), np.float32)
    shared = _overlap(frame, h, w)
    if shared is not None:
        full[shared[0]] = out[shared[1]]
    return full
