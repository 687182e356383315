"""A stack of slices interpolated to near-isotropic voxels: :func:`interpolate_stack`."""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

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
    _check_positive,
    _spacing_or_unit,
)
from tumor3d.geometry.interpolate.pair import _interpolate_gap, _paint, _parts, _select, _shrink


def slices_between_auto(slice_step_mm: float, pixel_spacing_mm: Sequence[float]) -> int:
    """Return the number of slices to insert per gap for near-isotropic voxels ([A10]).

    ``m = max(0, round(dz / dxy) - 1)`` with ``dz`` the slice step and
    ``dxy`` the mean in-plane spacing; halves round up.

    Parameters
    ----------
    slice_step_mm : float
        Centre-to-centre distance of consecutive slices ``dz``, mm.
    pixel_spacing_mm : (2,) sequence of float
        In-plane spacing ``(dy, dx)``, mm.

    Returns
    -------
    int
        ``m >= 0``.

    Raises
    ------
    InputError
        If a spacing is not a positive finite number, or
        ``pixel_spacing_mm`` does not have two entries.

    Examples
    --------
    >>> slices_between_auto(5.0, (1.0, 1.0))
    4
    >>> slices_between_auto(5.0, (0.9375, 0.9375))
    4
    """
    dz = _check_positive(slice_step_mm, "slice_step_mm")
    if (
        isinstance(pixel_spacing_mm, str | bytes)
        or np.ndim(pixel_spacing_mm) != 1
        or len(pixel_spacing_mm) != 2
    ):
        raise InputError(
            f"pixel_spacing_mm must be a pair (dy, dx) of mm, got {pixel_spacing_mm!r}"
        )
    dy = _check_positive(pixel_spacing_mm[0], "pixel_spacing_mm[0]")
    dx = _check_positive(pixel_spacing_mm[1], "pixel_spacing_mm[1]")
    ratio = dz / (0.5 * (dy + dx))
    return max(0, math.floor(ratio + 0.5) - 1)


@dataclass(frozen=True, eq=False)
class InterpolatedStack:
    """A slice stack with interpolated masks inserted between the acquired ones.

    Parameters
    ----------
    mask : (Z, y, x) bool ndarray
        The fine stack, ``Z = (n - 1)(m + 1) + 1`` for ``n`` acquired slices.
        Fine slice ``j`` lies at acquired-slice coordinate ``j / (m + 1)``;
        acquired slice ``k`` is copied unchanged to ``j = k (m + 1)``.
    slices_between : int
        ``m``, the number of slices inserted per gap.
    source_index : (Z,) float64 ndarray
        ``j / (m + 1)``: the position of each fine slice in acquired-slice
        index units.
    interpolated : (Z,) bool ndarray
        True where the fine slice was synthesised by interpolation, i.e. it
        is an inserted slice between two non-empty acquired masks. Inserted
        slices of other gaps are empty and False here.

    All arrays are copied and made read-only.
    """

    mask: np.ndarray
    slices_between: int
    source_index: np.ndarray
    interpolated: np.ndarray

    def __post_init__(self) -> None:
        mask = np.array(self.mask, dtype=bool)
        z = mask.shape[0] if mask.ndim == 3 else -1
        source_index = np.array(self.source_index, dtype=np.float64)
        interpolated = np.array(self.interpolated, dtype=bool)
        if mask.ndim != 3 or source_index.shape != (z,) or interpolated.shape != (z,):
            raise ValueError(
                "InterpolatedStack needs a (Z, y, x) mask and (Z,) source_index and "
                f"interpolated, got {mask.shape}, {source_index.shape}, {interpolated.shape}"
            )
        if int(self.slices_between) < 0:
            raise ValueError(f"slices_between must be >= 0, got {self.slices_between}")
        for arr in (mask, source_index, interpolated):
            arr.setflags(write=False)
        object.__setattr__(self, "mask", mask)
        object.__setattr__(self, "slices_between", int(self.slices_between))
        object.__setattr__(self, "source_index", source_index)
        object.__setattr__(self, "interpolated", interpolated)

    @property
    def original(self) -> np.ndarray:
        """(Z,) bool: True where the fine slice is an acquired slice."""
        return np.arange(self.mask.shape[0]) % (self.slices_between + 1) == 0

    def fine_affine(self, affine: np.ndarray) -> np.ndarray:
        """Affine of the fine stack in the world space of the scan.

        Parameters
        ----------
        affine : (4, 4) array_like
            The scan affine: voxel index ``(x, y, z, 1)`` of the acquired
            stack to RAS mm.

        Returns
        -------
        (4, 4) float64 ndarray
            The same with its z column divided by ``m + 1``, so fine slice
            ``j`` maps to the RAS position of acquired coordinate
            ``z = j / (m + 1)``.

        Raises
        ------
        InputError
            If ``affine`` is not 4x4.
        """
        aff = np.array(affine, dtype=np.float64)
        if aff.shape != (4, 4):
            raise InputError(f"affine must be 4x4, got shape {aff.shape}")
        aff[:3, 2] /= self.slices_between + 1
        return aff


def interpolate_stack(
    slice_masks: np.ndarray,
    *,
    method: Method = _DEFAULT_METHOD,
    slices_between: int | None,
    slice_step_mm: float | None = None,
    pixel_spacing_mm: Sequence[float] | None = None,
    end_caps: Literal["none", "taper"] = "none",
    parts: Parts = _DEFAULT_PARTS,
) -> InterpolatedStack:
    """Insert ``m`` interpolated masks between consecutive acquired slices.

    Only gaps whose two acquired masks are both non-empty are interpolated
    (see :func:`interpolate_pair`, at ``t = j / (m + 1)``, ``j = 1..m``);
    inserted slices of every other gap are empty, unless ``end_caps`` is
    ``"taper"``. Acquired slices are copied unchanged ("restore", step 5 of
    Algorithm 1). A stack without any tumour gives an all-empty fine stack;
    a single slice gives itself.

    End caps (an extension; the paper stops the object at its first and last
    abnormal slices). An object seen on slice ``k`` but not on ``k + 1``
    ends somewhere in between, and a flat cap at slice ``k`` loses that
    part. With ``end_caps="taper"`` the gap's inserted slices hold the end
    mask eroded linearly to nothing at the next acquired slice:
    ``{d >= t (max d + h/2)}`` with ``d`` the method's signed distance of the
    end mask (per part with ``parts="matched"``), a cone over a disk. For a
    sphere of radius ``R`` sampled at step ``h`` with a random phase, the cap
    beyond the last slice has expected volume ``pi R h^2 / 3``, and so does
    the cone ``A h / 3`` over the last slice's area ``A ~ 2 pi R a``: the cap
    is unbiased to first order in the continuous limit, while a flat cap
    always underestimates. On the pixel grid small end discs erode faster
    than ``(1 - t)^2`` in area, so a bias remains (measured with the chamfer
    metric, 1 mm pixels, 5 mm step, mean over 8 phases, mesh volume of a
    sphere of radius R: R = 8 mm -21.3 % flat vs -8.0 % taper; R = 10 mm
    -15.5 % vs -8.1 %; R = 14 mm -9.2 % vs -4.8 %; part of it is the chord
    error of interpolating between slices). Caps stop at the ends of the
    stack.

    Parameters
    ----------
    slice_masks : (n, y, x) array_like of bool
        Tumour masks of the acquired slices in increasing z order (empty on
        normal slices). The order is not checked (a mask carries no
        position): the caller sorts slices by their world position.
    method : {"shape-edt", "enhanced", "enhanced-edt", "shape", "linear"}
        Interpolation method (``InterpolateConfig.method``); see the module
        docstring.
    slices_between : int or None
        ``m >= 0`` (``InterpolateConfig.slices_between``). ``None`` means
        :func:`slices_between_auto` ([A10]), which then needs
        ``slice_step_mm`` and ``pixel_spacing_mm``. So a task can call
        ``interpolate_stack(masks, **cfg.model_dump(), slice_step_mm=...,
        pixel_spacing_mm=...)`` whatever the config holds.
    slice_step_mm : float, optional
        Slice step ``dz`` in mm; used only when ``slices_between`` is None.
    pixel_spacing_mm : (2,) sequence of float, optional
        In-plane spacing ``(dy, dx)`` in mm: for the automatic count and as
        the sampling of the Euclidean methods (default ``(1, 1)`` there).
    end_caps : {"none", "taper"}
        How the object ends beyond its first and last non-empty slices.
    parts : {"matched", "whole"}
        ``InterpolateConfig.parts``: interpolate matched 8-connected parts
        separately (unmatched ones shrink to nothing), or whole slices as
        Algorithm 1 does.

    Returns
    -------
    InterpolatedStack
        The fine stack; use :meth:`InterpolatedStack.fine_affine` for its
        geometry. Its slice step is ``dz / (m + 1)``.

    Raises
    ------
    InputError
        If ``slice_masks`` is not a non-empty 3-D binary array, ``method``,
        ``parts`` or ``end_caps`` is unknown, ``slices_between`` is not a
        non-negative integer, or it is None without both spacings.

    Examples
    --------
    >>> masks = np.zeros((3, 8, 8), dtype=bool); masks[1:, 2:6, 2:6] = True
    >>> st = interpolate_stack(masks, slices_between=1)
    >>> st.mask.shape, st.interpolated.tolist()
    ((5, 8, 8), [False, False, False, True, False])
    """
    masks = as_mask(slice_masks, "slice_masks", 3)
    meth = _check_method(method)
    prt = _check_parts(parts)
    if end_caps not in ("none", "taper"):
        raise InputError(f"unknown end_caps {end_caps!r}: expected 'none' or 'taper'")
    if slices_between is None:
        if slice_step_mm is None or pixel_spacing_mm is None:
            raise InputError(
                "slices_between is None (automatic, [A10]) but slice_step_mm and "
                "pixel_spacing_mm were not both given"
            )
        m = slices_between_auto(slice_step_mm, pixel_spacing_mm)
    else:
        if isinstance(slices_between, bool) or not isinstance(slices_between, numbers.Integral):
            raise InputError(f"slices_between must be an integer or None, got {slices_between!r}")
        m = int(slices_between)
        if m < 0:
            raise InputError(f"slices_between must be >= 0, got {m}")
    spacing = _spacing_or_unit(pixel_spacing_mm)

    n = masks.shape[0]
    step = m + 1
    n_fine = (n - 1) * step + 1
    fine = np.zeros((n_fine,) + masks.shape[1:], dtype=bool)
    fine[::step] = masks
    interpolated = np.zeros(n_fine, dtype=bool)
    nonempty = masks.reshape(n, -1).any(axis=1)
    ts = [j / step for j in range(1, step)]
    if m > 0:
        for k in range(n - 1):
            if nonempty[k] and nonempty[k + 1]:
                gap = _interpolate_gap(masks[k], masks[k + 1], ts, meth, prt, spacing)
                for j, sl in enumerate(gap, 1):
                    fine[k * step + j] = sl
                interpolated[k * step + 1 : (k + 1) * step] = True
    if end_caps == "taper" and m > 0:
        metric = _METHOD_SPEC[meth][0]
        for k in np.flatnonzero(nonempty):
            for direction in (1, -1):
                nxt = k + direction
                if 0 <= nxt < n and not nonempty[nxt]:
                    for j, sl in enumerate(_taper(masks[k], ts, metric, prt, spacing), 1):
                        fine[k * step + direction * j] = sl
                        interpolated[k * step + direction * j] = sl.any()
    return InterpolatedStack(
        mask=fine,
        slices_between=m,
        source_index=np.arange(n_fine) / step,
        interpolated=interpolated,
    )


def _taper(
    mask: np.ndarray,
    ts: Sequence[float],
    metric: str = "chamfer",
    parts: str = "whole",
    spacing: tuple[float, float] = (1.0, 1.0),
) -> list[np.ndarray]:
    """The end mask eroded to ``{d >= t (max d + h/2)}`` for each ``t`` (a cone cap).

    With ``parts="matched"`` each 8-connected part is its own cone.
    """
    if parts == "whole":
        d = _signed_distance(mask, metric, spacing)
        depth = float(d.max()) + half_step(metric, spacing)
        return [d >= t * depth for t in ts]
    labels, n = _parts(mask)
    pix = np.nonzero(labels)
    out = [np.zeros(mask.shape, dtype=bool) for _ in ts]
    for i in range(1, n + 1):
        for sl, ((ry, rx), offset) in zip(
            out, _shrink(_select(labels, pix, [i]), list(ts), metric, spacing), strict=True
        ):
            _paint(sl, ry, rx, offset)
    return out
