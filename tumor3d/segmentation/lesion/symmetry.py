"""Step 3c: the brain's mid-sagittal plane and the mirror test.

The left-right array axis from the scan's affine, the plane estimated by
maximal mirror correlation (:func:`symmetry_plane`), mirror images about it
and the seeds without a seed at their mirror position; see step 3c of
:mod:`tumor3d.segmentation.lesion`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft

from tumor3d.errors import InputError
from tumor3d.segmentation.lesion.normal import NormalModel
from tumor3d.segmentation.lesion.regions import _box_dilate

#: Step 3c: mirror tolerance (head roll / yaw of a few degrees, anatomical asymmetry), mm.
SYMMETRY_TOLERANCE_MM = 5.0


#: Step 3c: the mid-sagittal plane is searched over yaw angles within +- this (degrees)
#: of the left-right array axis's normal plane: a head in a scanner's head coil is
#: positioned to within a few degrees of yaw, clinical scans rarely exceed 10-15.
PLANE_MAX_YAW_DEG = 20.0


#: Step 3c: the grid (mm) on which the plane search resamples the slices; half of it
#: (1 mm) is the resolution of the plane's offset, far below the mirror tolerance.
PLANE_GRID_MM = 2.0


#: Step 3c: slices the plane search uses at most (of those whose brain area is at least
#: half the largest, evenly thinned).
PLANE_SLICES = 8


#: Step 3c: mirrored seeds within this in-plane distance of the kept asymmetric core are
#: regained. A tumour's own part removed by the mirror test lies in the band where a
#: voxel and its mirror are within the tolerance; twice the tolerance covers that band
#: on either side of the core. Leave-one-case-out over {5, 10, 20, inf} mm on the four
#: labelled real cases picks 10 for three of them (inf for pat0003), see
#: ``reports/segmentation.md``.
SYMMETRIC_REGAIN_MM = 2.0 * SYMMETRY_TOLERANCE_MM


@dataclass(frozen=True)
class MirrorPlane:
    """The brain's mid-sagittal plane: the same line in every slice (step 3c).

    In a slice's ``(y, x)`` plane in mm (``p = (row * dy, column * dx)``,
    pixel ``(0, 0)`` at the origin) the plane is the line ``n . p =
    offset_mm``. Its unit normal ``n`` is the left-right array axis's unit
    vector turned by ``yaw_deg``: ``(-sin a, cos a)`` when ``axis`` is 2
    (columns run left-right), ``(cos a, sin a)`` when it is 1. The mirror of
    ``p`` is ``p - 2 (n . p - offset_mm) n``.

    Attributes
    ----------
    axis : {1, 2}
        The left-right array axis (of ``(z, y, x)``).
    yaw_deg : float
        The head's yaw: angle between the plane and that axis's normal plane.
    offset_mm : float
        Signed distance of the line from pixel ``(0, 0)`` along ``n``, mm.
    """

    axis: int
    yaw_deg: float
    offset_mm: float

    def normal(self) -> np.ndarray:
        """The unit normal ``n`` (``(y, x)`` components)."""
        return _plane_frame(self.axis, self.yaw_deg)[1]

    def signed_distance_mm(
        self, shape: tuple[int, int], pixel_mm: tuple[float, float]
    ) -> np.ndarray:
        """``n . p - offset_mm`` of every pixel of a ``(y, x)`` slice grid, in mm.

        ``pixel_mm`` is the ``(row, column)`` pixel size; the sign tells the
        side of the plane (the same in every slice).
        """
        n = self.normal()
        y, x = np.indices(shape, dtype=np.float64)
        return (y * float(pixel_mm[0])) * n[0] + (x * float(pixel_mm[1])) * n[1] - self.offset_mm


def _plane_frame(axis: int, yaw_deg: float) -> tuple[np.ndarray, np.ndarray]:
    """(tangent, normal) unit vectors in ``(y, x)`` of the plane at ``yaw_deg``."""
    a = np.deg2rad(float(yaw_deg))
    along_y = np.array([np.cos(a), np.sin(a)])
    along_x = np.array([-np.sin(a), np.cos(a)])
    return (along_y, along_x) if axis == 2 else (along_x, along_y)


def left_right_axis(affine: np.ndarray) -> int | None:
    """Array axis (of ``(z, y, x)``) that runs left-right, from a RAS affine.

    ``affine`` maps the voxel index ``(x, y, z, 1)`` to RAS mm (the `Scan`
    convention). The index whose direction is nearest the R axis is the
    left-right one; None if that is the slice axis (sagittal slices: no
    in-plane mirror) or no axis lies within 45 degrees of R.
    """
    a = np.asarray(affine, dtype=np.float64)[:3, :3]
    cos = np.abs(a[0]) / np.maximum(np.linalg.norm(a, axis=0), 1e-12)
    j = int(np.argmax(cos))
    if cos[j] < np.sqrt(0.5) or j == 2:
        return None
    return 2 - j  # index x -> array axis 2, y -> 1


def symmetry_plane(
    smoothed: np.ndarray,
    brain: np.ndarray,
    model: NormalModel,
    axis: int,
    voxel_mm: tuple[float, ...],
) -> MirrorPlane:
    """Step 3c: the brain's mid-sagittal plane, by maximal mirror correlation.

    Normal anatomy is left-right symmetric about the mid-sagittal plane, but
    a head is not always straight in the scanner: a yaw of a few degrees puts
    the plane's far ends centimetres away from the array's middle column,
    beyond any mirror tolerance. The plane (yaw and offset; the same line on
    every slice) is the one about which the image best matches its own
    mirror image, the classical criterion of symmetry-plane estimation
    (Tuzikov, Colliot and Bloch, *Med. Image Anal.* 7(4), 2003): over yaw
    angles within :data:`PLANE_MAX_YAW_DEG` (2 degree steps on a grid of
    twice :data:`PLANE_GRID_MM`, then 0.25 degree steps within 1 degree of the
    best on the :data:`PLANE_GRID_MM` grid, or on the pixels where they are
    coarser), the slices are resampled on a
    grid aligned with the candidate plane, and the mirror correlation of
    every offset at once is the autoconvolution of its rows (FFT). The gray
    levels are the smoothed ones clipped to the normal range ``mu +- 2
    sigma``, so that the tumour and fluid pull the plane no more than
    normal tissue of the same extent would (a bright lesion still weighs:
    on a small synthetic brain it moved the plane by up to 3 degrees), and
    shifted so that the brain is brighter than the background (its outline
    counts). The slices are those whose brain area is at least half the
    largest (they carry the outline and the midline best), evenly thinned
    to at most :data:`PLANE_SLICES`. A brain cut by the field of view biases
    the estimate (its outline is no longer symmetric); so did the array's
    middle column, the rule before. ``yaw_deg`` is in array terms (the
    sense of ``scipy.ndimage.rotate(..., axes=(1, 2))``), not the patient's.

    Parameters
    ----------
    smoothed : (z, y, x) ndarray
        Step 1's smoothed gray levels.
    brain : (z, y, x) ndarray of bool
    model : NormalModel
        The normal-tissue model (its median and sigma clip the gray levels).
    axis : {1, 2}
        The left-right array axis.
    voxel_mm : (3,) tuple of float
        Voxel spacing ``(slice step, row, column)``, mm.

    Returns
    -------
    MirrorPlane
        Yaw within :data:`PLANE_MAX_YAW_DEG`; among equal scores the smallest
        yaw. When no yaw scores at all (no structure: a score that is not
        finite and positive), the plane through the brain's centroid at yaw 0
        (the rule before the plane was estimated).

    Raises
    ------
    InputError
        If ``axis`` is not an in-plane axis, the brain is empty or the pixel
        spacing is not positive.
    """
    if axis not in (1, 2):
        raise InputError(f"lr_axis must be 1 or 2 (an in-plane axis), got {axis}")
    dy, dx = float(voxel_mm[1]), float(voxel_mm[2])
    if not (np.isfinite(dy) and np.isfinite(dx) and dy > 0 and dx > 0):
        raise InputError(f"pixel spacing must be positive, got {(dy, dx)} mm")
    if not np.any(brain):
        raise InputError("symmetry_plane needs a non-empty brain mask")
    area = brain.sum(axis=(1, 2))
    zs = np.flatnonzero(area >= 0.5 * area.max())
    if zs.size > PLANE_SLICES:
        zs = zs[np.linspace(0, zs.size - 1, PLANE_SLICES).round().astype(np.intp)]
    lo, hi = model.median - 2.0 * model.sigma, model.median + 2.0 * model.sigma
    f = np.where(brain[zs], np.clip(smoothed[zs], lo, hi) - lo + model.sigma, 0.0)
    ys, xs = np.nonzero(brain[zs].any(axis=0))
    centre = np.array([ys.mean() * dy, xs.mean() * dx])
    radius = float(np.sqrt((ys * dy - centre[0]) ** 2 + (xs * dx - centre[1]) ** 2).max())
    f = f.astype(np.float32)
    # never finer than the pixels: the grid's size stays bounded by the array's
    grid_mm = max(PLANE_GRID_MM, min(dy, dx))

    def score(yaw: float, step_mm: float) -> tuple[float, float]:
        k = int(np.ceil(radius / step_mm)) + 2
        grid = np.arange(-k, k + 1) * step_mm
        v, u = np.meshgrid(grid, grid, indexing="ij")  # rows along the plane, columns across
        t, n = _plane_frame(axis, yaw)
        r = _bilinear(
            f, (centre[0] + u * n[0] + v * t[0]) / dy, (centre[1] + u * n[1] + v * t[1]) / dx
        )
        m = r.shape[2]
        spec = scipy.fft.rfft(r, n=2 * m, axis=2)
        # sum_j r(j) r(i - j): the match of the columns j and i - j, mirrored about i / 2
        conv = scipy.fft.irfft(spec * spec, n=2 * m, axis=2).sum(axis=(0, 1))[: 2 * m - 1]
        i = int(np.argmax(conv))
        energy = float((r.astype(np.float64) ** 2).sum())
        offset = float(n @ centre) + (i / 2.0 - k) * step_mm
        return float(conv[i]) / max(energy, 1e-12), offset

    # coarse: 2 degree steps on a grid twice as coarse (the score is smooth in the yaw:
    # the brain's outline and midline are large); fine: 0.25 degree steps around the best
    # (ties go to the smallest yaw)
    coarse = np.arange(-PLANE_MAX_YAW_DEG, PLANE_MAX_YAW_DEG + 1e-9, 2.0)
    best = max(coarse, key=lambda a: (score(a, 2.0 * grid_mm)[0], -abs(a)))
    fine = best + np.arange(-1.0, 1.01, 0.25)
    fine = fine[np.abs(fine) <= PLANE_MAX_YAW_DEG + 1e-9]
    scored = [(score(a, grid_mm), float(a)) for a in fine]
    (value, offset), yaw = max(scored, key=lambda sa: (sa[0][0], -abs(sa[1])))
    if not (np.isfinite(value) and value > 0):
        return MirrorPlane(int(axis), 0.0, float(_plane_frame(axis, 0.0)[1] @ centre))
    return MirrorPlane(int(axis), yaw, offset)


def _bilinear(f: np.ndarray, y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Every slice of ``f`` sampled at the fractional pixels ``(y, x)`` (bilinear, zero padded).

    Equal to ``scipy.ndimage.map_coordinates(order=1, mode="grid-constant",
    cval=0)`` on each slice: beyond the last pixel centre the neighbour outside
    counts as 0.

    The sample points are the same on every slice, so the four neighbours are
    gathered for all slices at once (scipy's ``map_coordinates`` would
    interpolate along the slices too).
    """
    ny, nx = f.shape[1:]
    y0 = np.floor(y).astype(np.intp)
    x0 = np.floor(x).astype(np.intp)
    wy = (y - y0).astype(np.float32)
    wx = (x - x0).astype(np.float32)
    out = np.zeros((f.shape[0], *y.shape), dtype=np.float32)
    for oy, ox, w in ((0, 0, (1 - wy) * (1 - wx)), (0, 1, (1 - wy) * wx),
                      (1, 0, wy * (1 - wx)), (1, 1, wy * wx)):  # fmt: skip
        iy, ix = y0 + oy, x0 + ox
        ok = (iy >= 0) & (iy < ny) & (ix >= 0) & (ix < nx)
        out += np.where(ok, w, 0.0) * f[:, np.clip(iy, 0, ny - 1), np.clip(ix, 0, nx - 1)]
    return out


def _mirror_index(
    shape: tuple[int, int], plane: MirrorPlane, voxel_mm: tuple[float, ...]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest pixel of each pixel's mirror image: (rows, columns, inside the grid)."""
    dy, dx = float(voxel_mm[1]), float(voxel_mm[2])
    n = plane.normal()
    s = 2.0 * plane.signed_distance_mm(shape, (dy, dx))
    y, x = np.indices(shape, dtype=np.float64)
    iy = np.rint((y * dy - s * n[0]) / dy).astype(np.intp)
    ix = np.rint((x * dx - s * n[1]) / dx).astype(np.intp)
    ok = (iy >= 0) & (iy < shape[0]) & (ix >= 0) & (ix < shape[1])
    return iy, ix, ok


def mirror_image(a: np.ndarray, plane: MirrorPlane, voxel_mm: tuple[float, ...]) -> np.ndarray:
    """Every slice of ``a`` reflected about ``plane`` (nearest pixel); 0 outside the grid.

    ``a`` is ``(z, y, x)``; ``voxel_mm`` is ``(slice step, row, column)`` in mm and
    ``plane`` is in ``a``'s pixel frame.

    Examples
    --------
    >>> a = np.zeros((1, 1, 5), int); a[0, 0, :] = [1, 2, 3, 4, 5]
    >>> mirror_image(a, MirrorPlane(2, 0.0, 2.0), (1.0, 1.0, 1.0))[0, 0].tolist()
    [5, 4, 3, 2, 1]
    """
    iy, ix, ok = _mirror_index(a.shape[1:], plane, voxel_mm)
    out = np.zeros_like(a)
    out[:, ok] = a[:, iy[ok], ix[ok]]
    return out


def _shifted_plane(plane: MirrorPlane, dy_mm: float, dx_mm: float) -> MirrorPlane:
    """The same plane with the pixel frame's origin moved by ``(-dy_mm, -dx_mm)``."""
    n = plane.normal()
    offset = plane.offset_mm + float(n[0]) * dy_mm + float(n[1]) * dx_mm
    return MirrorPlane(plane.axis, plane.yaw_deg, float(offset))


def _asymmetric_seeds(
    seeds: np.ndarray, plane: MirrorPlane, voxel_mm: tuple[float, ...]
) -> np.ndarray:
    """Step 3c: the seeds whose mirror position (within the tolerance) holds no seed."""
    half = [int(round(SYMMETRY_TOLERANCE_MM / float(voxel_mm[ax]))) for ax in (1, 2)]
    mirrored = _box_dilate(mirror_image(seeds, plane, voxel_mm), half[0], half[1])
    return seeds & ~mirrored


def _mirrored(mask: np.ndarray, plane: MirrorPlane, voxel_mm) -> np.ndarray:
    """Voxels of ``mask`` whose mirror position (within the tolerance) is in ``mask``."""
    return mask & ~_asymmetric_seeds(mask, plane, voxel_mm)
