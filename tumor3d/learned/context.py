"""Auto-context features: what a first forest's probability map says around each pixel.

Auto-context (Tu & Bai 2010, doi:10.1109/TPAMI.2009.186; the BraTS 2013
forest of Tustison et al. 2015) trains a second classifier on the first
one's features plus features of the first one's probability map, so that a
pixel's decision can use the decisions around it: the map smoothed at three
in-plane scales, its values in the neighbouring slices and on a ring around
the pixel, the distance to the lesion the first stage would keep, and the
slice's peak, mean and lesion area. The second stage must be trained on
probabilities the first stage gives to patients it was not trained on
(out-of-fold), as it will see at inference.

Arrays are ``(z, y, x)``, ``z`` the slice axis. Nothing here reads a file.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from tumor3d.errors import InputError

__all__ = ["CONTEXT_NAMES", "context_features"]

#: In-plane Gaussian scales (mm) of the smoothed probability.
_CTX_SMOOTH_MM = (2.0, 4.0, 8.0)

#: Radius (mm) of the ring of eight in-plane offsets.
RING_MM = 10.0

#: Clip (mm) of the distances to the first stage's lesion.
CONTEXT_DISTANCE_CLIP_MM = 30.0

CONTEXT_NAMES: tuple[str, ...] = (
    "s1_prob",
    *(f"s1_smooth_{s:g}mm" for s in _CTX_SMOOTH_MM),
    "s1_neighbour_mean",
    "s1_neighbour_max",
    "s1_ring_max",
    "s1_ring_min",
    "s1_distance_mm",
    "s1_distance_3d_mm",
    "s1_slice_max",
    "s1_slice_mean",
    "s1_slice_area",
)


def _offset(a: np.ndarray, dy: int, dx: int) -> np.ndarray:
    """``out[z, y, x] = a[z, y + dy, x + dx]``; 0 beyond the edge."""
    out = np.zeros_like(a)
    ny, nx = a.shape[1:]
    ys, yd = (slice(dy, ny), slice(0, ny - dy)) if dy >= 0 else (slice(0, ny + dy), slice(-dy, ny))
    xs, xd = (slice(dx, nx), slice(0, nx - dx)) if dx >= 0 else (slice(0, nx + dx), slice(-dx, nx))
    out[:, yd, xd] = a[:, ys, xs]
    return out


def context_features(
    probability: np.ndarray,
    lesion: np.ndarray,
    *,
    candidates: np.ndarray,
    index: np.ndarray,
    spacing_mm: tuple[float, float, float],
) -> np.ndarray:
    """The :data:`CONTEXT_NAMES` columns of the pixels ``index`` (flat, as the features').

    Parameters
    ----------
    probability : (z, y, x) ndarray of float
        The first stage's lesion probability (0 outside the tissue).
    lesion : (z, y, x) ndarray of bool
        The lesion the first stage keeps (:func:`~tumor3d.learned.segment.keep_main_lesion`).
    candidates : (z, y, x) ndarray of bool
        The tissue pixels (``PatientFeatures.candidates``): the slice mean's support.
    index : (n,) ndarray of int
        Flat indices of the rows (``PatientFeatures.index``).
    spacing_mm : (3,) tuple of float
        ``(slice step, row, column)`` in mm.

    Returns
    -------
    (n, len(CONTEXT_NAMES)) ndarray of float32

    Examples
    --------
    A pixel inside a bright square sees a high ring minimum; one far from
    it is 30 mm (the clip) from the lesion:

    >>> p = np.zeros((3, 40, 80), np.float32); p[:, 5:35, 5:35] = 0.9
    >>> tissue = np.ones(p.shape, bool)
    >>> idx = np.ravel_multi_index(([1, 1], [20, 0], [20, 79]), p.shape)
    >>> c = context_features(p, p > 0.5, candidates=tissue, index=idx, spacing_mm=(5.0, 1.0, 1.0))
    >>> [round(float(v), 2) for v in c[:, CONTEXT_NAMES.index("s1_ring_min")]]
    [0.89, 0.0]
    >>> [round(float(v), 1) for v in c[:, CONTEXT_NAMES.index("s1_distance_mm")]]
    [-15.0, 30.0]
    """
    prob = np.asarray(probability, dtype=np.float32)
    les = np.asarray(lesion, dtype=bool)
    cand = np.asarray(candidates, dtype=bool)
    if prob.ndim != 3 or les.shape != prob.shape or cand.shape != prob.shape:
        raise InputError(
            f"probability {prob.shape}, lesion {les.shape} and candidates {cand.shape} "
            "must be one 3-D shape"
        )
    sp = tuple(float(v) for v in np.ravel(spacing_mm))
    if len(sp) != 3 or not all(np.isfinite(v) and v > 0 for v in sp):
        raise InputError(f"spacing_mm must be three positive numbers, got {spacing_mm}")
    idx = np.asarray(index, dtype=np.int64)
    pixel_mm = (sp[1], sp[2])
    clip = CONTEXT_DISTANCE_CLIP_MM
    nz = prob.shape[0]
    cols: list[np.ndarray] = [prob]
    smooth = {
        s: ndi.gaussian_filter(prob, (0.0, s / pixel_mm[0], s / pixel_mm[1]), mode="constant")
        for s in _CTX_SMOOTH_MM
    }
    cols += [smooth[s] for s in _CTX_SMOOTH_MM]
    s2 = smooth[2.0]
    up = np.concatenate([s2[1:], s2[-1:]], axis=0)
    down = np.concatenate([s2[:1], s2[:-1]], axis=0)
    cols += [0.5 * (up + down), np.maximum(up, down)]
    ring = []
    for ang in np.arange(8) * (np.pi / 4.0):
        dy = int(round(RING_MM * np.sin(ang) / pixel_mm[0]))
        dx = int(round(RING_MM * np.cos(ang) / pixel_mm[1]))
        ring.append(_offset(s2, dy, dx))
    ring_arr = np.stack(ring)
    cols += [ring_arr.max(axis=0), ring_arr.min(axis=0)]
    dist = np.full(prob.shape, clip, np.float32)
    for z in range(nz):
        if les[z].any():
            outside = ndi.distance_transform_edt(~les[z], sampling=pixel_mm)
            inside = ndi.distance_transform_edt(les[z], sampling=pixel_mm)
            dist[z] = np.clip(outside - inside, -clip, clip)
    cols.append(dist)
    if les.any():
        d3 = ndi.distance_transform_edt(~les, sampling=sp).astype(np.float32)
        cols.append(np.minimum(d3, clip))
    else:
        cols.append(np.full(prob.shape, clip, np.float32))
    cols.append(np.broadcast_to(prob.reshape(nz, -1).max(axis=1)[:, None, None], prob.shape))
    n_cand = np.maximum(cand.sum(axis=(1, 2)), 1)
    mean = (np.where(cand, prob, 0.0).sum(axis=(1, 2)) / n_cand).astype(np.float32)
    cols.append(np.broadcast_to(mean[:, None, None], prob.shape))
    area = les.sum(axis=(1, 2)).astype(np.float32)
    share = area / max(float(area.max()), 1.0)
    cols.append(np.broadcast_to(share[:, None, None], prob.shape))
    out = np.empty((idx.size, len(cols)), dtype=np.float32)
    for j, c in enumerate(cols):
        out[:, j] = np.broadcast_to(c, prob.shape).ravel()[idx]
    return out
