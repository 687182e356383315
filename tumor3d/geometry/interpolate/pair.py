"""Algorithm 1 between two slices: :func:`interpolate_pair`, whole slices or matched parts.

Masks are placed on the unbounded pixel plane (shifts by whole pixels),
matched part by part (``parts="matched"``) and interpolated group by
group; see :mod:`tumor3d.geometry.interpolate`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy import ndimage as ndi

from tumor3d.errors import InputError
from tumor3d.geometry.distance import (
    _signed_distance,
    as_mask,
    half_step,
)
from tumor3d.geometry.interpolate.methods import (
    _DEFAULT_METHOD,
    _DEFAULT_PARTS,
    _METHOD_SPEC,
    Method,
    Parts,
    _check_method,
    _check_parts,
    _check_t,
    _spacing_or_unit,
)

# 8-connectivity for the parts of a slice
_EIGHT = np.ones((3, 3), dtype=bool)


def _centroid(ys: np.ndarray, xs: np.ndarray) -> np.ndarray:
    return np.array([ys.mean(), xs.mean()])


def _rint(v: np.ndarray) -> np.ndarray:
    """Round to the nearest integer, halves up.

    Unlike half-to-even, this commutes with integer translations, so the
    result does not depend on where the grid is.
    """
    return np.floor(v + 0.5).astype(np.int64)


def _place(
    shape: tuple[int, int], ys: np.ndarray, xs: np.ndarray, offset: np.ndarray
) -> np.ndarray:
    """Bool mask of ``shape`` with pixels ``(ys, xs) + offset`` set; zero fill, no wrap."""
    out = np.zeros(shape, dtype=bool)
    _paint(out, ys, xs, offset)
    return out


def _paint(out: np.ndarray, ys: np.ndarray, xs: np.ndarray, offset: np.ndarray) -> None:
    """Set pixels ``(ys, xs) + offset`` of ``out`` (in place on a mask we own); no wrap."""
    yy = ys + offset[0]
    xx = xs + offset[1]
    keep = (yy >= 0) & (yy < out.shape[0]) & (xx >= 0) & (xx < out.shape[1])
    out[yy[keep], xx[keep]] = True


def _window(*pix: tuple[np.ndarray, np.ndarray]) -> tuple[list[np.ndarray], np.ndarray]:
    """Rasterise pixel sets on their common bounding box.

    Returns the bool masks of the box (one per set) and its origin ``(y0, x0)``
    in the coordinates of the pixel sets.
    """
    lo = np.array([min(p[0].min() for p in pix), min(p[1].min() for p in pix)])
    hi = np.array([max(p[0].max() for p in pix), max(p[1].max() for p in pix)])
    shape = tuple(int(s) for s in hi - lo + 1)
    out = []
    for p in pix:
        w = np.zeros(shape, dtype=bool)
        w[p[0] - lo[0], p[1] - lo[1]] = True
        out.append(w)
    return out, lo


Pixels = tuple[np.ndarray, np.ndarray]


def _interp_group(
    a: Pixels,
    b: Pixels,
    ts: Sequence[float],
    metric: str,
    align: bool,
    centre: np.ndarray,
    spacing: tuple[float, float],
) -> list[tuple[Pixels, np.ndarray]]:
    """Shape-based interpolation of two non-empty pixel sets at every ``t``.

    Returns, per ``t``, the pixels of the result and the offset to add to them.
    With ``align`` this is Algorithm 1 (steps 1-4, 6, 7) around ``centre``.
    """
    ya, xa = a
    yb, xb = b
    if align:
        c_s = _centroid(ya, xa)  # step 2
        c_t = _centroid(yb, xb)
        shift_a = _rint(centre - c_s)  # step 3, on the unbounded plane
        shift_b = _rint(centre - c_t)
    else:
        shift_a = shift_b = np.zeros(2, dtype=np.int64)
    (wa, wb), origin = _window(
        (ya + shift_a[0], xa + shift_a[1]), (yb + shift_b[0], xb + shift_b[1])
    )
    da = _signed_distance(wa, metric, spacing)  # step 4
    db = _signed_distance(wb, metric, spacing)
    out: list[tuple[Pixels, np.ndarray]] = []
    for t in ts:
        ry, rx = np.nonzero((1.0 - t) * da + t * db >= 0.0)  # R' = {d_t >= 0}
        if not align or ry.size == 0:
            out.append(((ry, rx), origin))
            continue
        c_z = (1.0 - t) * c_s + t * c_t  # step 6
        # step 7 [A13]: move R' so its centroid lands on C_z (to the nearest pixel)
        shift = _rint(c_z - (_centroid(ry, rx) + origin))
        out.append(((ry, rx), origin + shift))
    return out


def _shrink(
    p: Pixels, fractions: Sequence[float], metric: str, spacing: tuple[float, float]
) -> list[tuple[Pixels, np.ndarray]]:
    """The pixel set eroded to ``{d >= f (max d + h/2)}`` for each fraction ``f`` (a cone)."""
    (w,), origin = _window(p)
    d = _signed_distance(w, metric, spacing)
    depth = float(d.max()) + half_step(metric, spacing)
    return [(np.nonzero(d >= f * depth), origin) for f in fractions]


def _parts(mask: np.ndarray) -> tuple[np.ndarray, int]:
    labels, n = ndi.label(mask, structure=_EIGHT)
    return labels, int(n)


def _pairs(i: np.ndarray, j: np.ndarray, nb: int) -> set[tuple[int, int]]:
    """The distinct label pairs ``(i, j)`` of two aligned label arrays."""
    keys = np.unique(i.astype(np.int64) * (nb + 1) + j)
    return {(int(k // (nb + 1)), int(k % (nb + 1))) for k in keys}


def _match_parts(
    la: np.ndarray, na: int, lb: np.ndarray, nb: int, align: bool
) -> tuple[list[tuple[list[int], list[int]]], list[int], list[int]]:
    """Group the parts of two labelled slices by overlap.

    Returns the groups ``(labels of a, labels of b)`` (connected components
    of the bipartite overlap graph), the unmatched labels of ``a`` and those
    of ``b``. Overlap is tested in place and, with ``align``, also after
    moving ``b`` onto ``a`` by the rounded difference of the whole-slice
    centroids (Algorithm 1's alignment).
    """
    both = (la > 0) & (lb > 0)
    edges = _pairs(la[both], lb[both], nb)
    if align:
        yb, xb = np.nonzero(lb)
        ya, xa = np.nonzero(la)
        s = _rint(_centroid(ya, xa) - _centroid(yb, xb))
        yy, xx = yb + s[0], xb + s[1]
        keep = (yy >= 0) & (yy < la.shape[0]) & (xx >= 0) & (xx < la.shape[1])
        hit_a = la[yy[keep], xx[keep]]
        hit_b = lb[yb[keep], xb[keep]]
        sel = hit_a > 0
        edges |= _pairs(hit_a[sel], hit_b[sel], nb)
    # union-find over a-nodes 1..na and b-nodes na+1..na+nb
    parent = list(range(na + nb + 1))

    def find(u: int) -> int:
        while parent[u] != u:
            parent[u] = parent[parent[u]]
            u = parent[u]
        return u

    for i, j in edges:
        ri, rj = find(i), find(na + j)
        if ri != rj:
            parent[ri] = rj
    groups: dict[int, tuple[list[int], list[int]]] = {}
    matched_a = {i for i, _ in edges}
    matched_b = {j for _, j in edges}
    for i in sorted(matched_a):
        groups.setdefault(find(i), ([], []))[0].append(i)
    for j in sorted(matched_b):
        groups.setdefault(find(na + j), ([], []))[1].append(j)
    unmatched_a = [i for i in range(1, na + 1) if i not in matched_a]
    unmatched_b = [j for j in range(1, nb + 1) if j not in matched_b]
    return list(groups.values()), unmatched_a, unmatched_b


def _select(labels: np.ndarray, pix: Pixels, wanted: list[int]) -> Pixels:
    """The pixels of ``pix`` whose label is in ``wanted``."""
    lut = np.zeros(int(labels.max()) + 1, dtype=bool)
    lut[wanted] = True
    sel = lut[labels[pix]]
    return pix[0][sel], pix[1][sel]


def _interpolate_gap(
    mask_a: np.ndarray,
    mask_b: np.ndarray,
    ts: Sequence[float],
    method: str,
    parts: str = "whole",
    spacing: tuple[float, float] = (1.0, 1.0),
) -> list[np.ndarray]:
    """Interpolated masks at every fraction of ``ts``; the distances are computed once per group.

    ``mask_a`` and ``mask_b`` are validated bool arrays of one shape.
    """
    shape = mask_a.shape
    if not mask_a.any() or not mask_b.any():
        return [np.zeros(shape, dtype=bool) for _ in ts]
    if method == "linear":
        fa = mask_a.astype(np.float64)
        fb = mask_b.astype(np.float64)
        return [(1.0 - t) * fa + t * fb >= 0.5 for t in ts]

    metric, align = _METHOD_SPEC[method]
    centre = np.array([(shape[0] - 1) / 2.0, (shape[1] - 1) / 2.0])  # step 1: C
    out = [np.zeros(shape, dtype=bool) for _ in ts]
    if parts == "whole":
        pieces = [
            _interp_group(
                np.nonzero(mask_a), np.nonzero(mask_b), ts, metric, align, centre, spacing
            )
        ]
    else:
        # work on the bounding box of both masks (labelling is the cost); box
        # coordinates + lo = grid coordinates (shifts are translation invariant)
        rows = np.flatnonzero((mask_a | mask_b).any(axis=1))
        cols = np.flatnonzero((mask_a | mask_b).any(axis=0))
        lo = np.array([rows[0], cols[0]])
        box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
        la, na = _parts(mask_a[box])
        lb, nb = _parts(mask_b[box])
        pa = np.nonzero(la)
        pb = np.nonzero(lb)
        groups, lone_a, lone_b = _match_parts(la, na, lb, nb, align)
        c_box = centre - lo
        pieces = [
            _interp_group(
                _select(la, pa, ga), _select(lb, pb, gb), ts, metric, align, c_box, spacing
            )
            for ga, gb in groups
        ]
        # parts without a partner shrink to nothing towards the other slice
        pieces += [_shrink(_select(la, pa, [i]), list(ts), metric, spacing) for i in lone_a]
        pieces += [
            _shrink(_select(lb, pb, [j]), [1.0 - t for t in ts], metric, spacing) for j in lone_b
        ]
        pieces = [[(pix, off + lo) for pix, off in piece] for piece in pieces]
    for piece in pieces:
        for sl, ((ry, rx), offset) in zip(out, piece, strict=True):
            _paint(sl, ry, rx, offset)
    return out


def interpolate_pair(
    mask_a: np.ndarray,
    mask_b: np.ndarray,
    t: float,
    *,
    method: Method = _DEFAULT_METHOD,
    parts: Parts = _DEFAULT_PARTS,
    pixel_spacing_mm: Sequence[float] | None = None,
) -> np.ndarray:
    """Interpolate one mask at fraction ``t`` between two slice masks.

    ``method="enhanced"`` with ``parts="whole"`` is Algorithm 1 of [P]:

    1. ``C = ((H - 1)/2, (W - 1)/2)``, the grid centre ([A12]);
    2. ``C_s``, ``C_t``: centroids (mean pixel position) of ``mask_a``, ``mask_b``;
    3. shift ``mask_a`` by ``round(C - C_s)`` and ``mask_b`` by
       ``round(C - C_t)`` (integer shifts, zero fill);
    4. ``d_t = (1 - t) d_a + t d_b`` of the chamfer signed distances
       (:func:`tumor3d.geometry.distance.signed_distance`) and ``R' = {d_t >= 0}``;
    5. (the originals are kept unchanged by :func:`interpolate_stack`);
    6. ``C_z = (1 - t) C_s + t C_t``;
    7. the output is ``R'`` shifted by ``round(C_z - centroid(R'))`` ([A13]),
       so its centroid is within half a pixel of ``C_z`` per axis (unless
       the image border cuts it).

    ``round`` rounds halves up (``floor(v + 1/2)``), which, unlike
    half-to-even, commutes with integer translations of the grid.

    ``"enhanced-edt"`` is the same with the exact Euclidean distance in mm;
    ``"shape"`` (SO baseline) thresholds ``(1 - t) d_a + t d_b`` of the
    unaligned city-block signed distances and ``"shape-edt"`` of the
    unaligned Euclidean ones; ``"linear"`` (LG mask variant, [A14])
    thresholds ``(1 - t) a + t b >= 1/2``. With ``parts="matched"`` the
    8-connected parts are matched by overlap and interpolated group by
    group (package docstring).

    Parameters
    ----------
    mask_a, mask_b : (y, x) array_like of bool
        Tumour masks of two consecutive acquired slices, same shape.
    t : float
        Fraction in the open interval (0, 1); ``t -> 0`` approaches ``mask_a``.
    method : {"shape-edt", "enhanced", "enhanced-edt", "shape", "linear"}
        Interpolation method.
    parts : {"matched", "whole"}
        Interpolate matched parts separately, or whole slices (the paper).
    pixel_spacing_mm : (2,) sequence of float, optional
        In-plane spacing ``(dy, dx)`` in mm for the Euclidean methods
        (default ``(1, 1)``; only the ratio ``dy/dx`` matters). Ignored by
        the pixel metrics.

    Returns
    -------
    (y, x) bool ndarray
        The interpolated mask. If either input mask is empty the result is
        empty (there is no shape to interpolate towards; :func:`interpolate_stack`
        handles ends with ``end_caps``); with ``parts="whole"`` it can also
        be empty when the two shapes do not overlap after alignment (or, for
        the unaligned methods, at all).

    Raises
    ------
    InputError
        If a mask is not a non-empty 2-D binary array, the shapes differ,
        ``t`` is not in (0, 1), ``method`` or ``parts`` is unknown, or a
        spacing is not positive.

    Examples
    --------
    >>> a = np.zeros((9, 9), dtype=bool); a[2:5, 1:4] = True
    >>> b = np.zeros((9, 9), dtype=bool); b[2:5, 5:8] = True
    >>> np.argwhere(interpolate_pair(a, b, 0.5, method="enhanced")).mean(axis=0)
    array([3., 4.])
    """
    a = as_mask(mask_a, "mask_a", 2)
    b = as_mask(mask_b, "mask_b", 2)
    if a.shape != b.shape:
        raise InputError(f"mask_a and mask_b must have the same shape, got {a.shape} and {b.shape}")
    tt = _check_t(t)
    meth = _check_method(method)
    prt = _check_parts(parts)
    sp = _spacing_or_unit(pixel_spacing_mm)
    return _interpolate_gap(a, b, [tt], meth, prt, sp)[0]
