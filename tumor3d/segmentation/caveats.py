"""Caveats of a segmentation: where its volume may be wrong, said in words.

A volume is only as good as the mask it measures. Two situations are known
to bias it and can be recognised from the mask alone, and a third (a lesion
found without the symmetry rule's confirmation) is known from the lesion
model, so the pipeline says so in the run's notes (summary,
``metrics.parquet``, ``provenance.json``) instead of reporting a number that
looks as trustworthy as any other:

- **The tumour reaches the first or last slice of the scan.** It may
  continue beyond the scanned range; every volume may then underestimate
  it.
- **The tumour reaches the brain's midline** (robust method). The
  symmetry rule of :mod:`tumor3d.segmentation.lesion` (step 3c) counts a bright voxel
  as lesion only where its mirror image is not bright too: it cannot tell
  the far side of a tumour that crosses the midline (its mirror is the
  tumour itself) from a bilateral normal structure. Within half the
  symmetry tolerance of the mid-sagittal plane every voxel is its own
  mirror match, so the rule is blind there; a lesion reaching that band
  over a significant cross-section (as a seed component must be:
  ``min_region_mm2`` on ``min_slices`` consecutive slices) may have
  lost a part in the other hemisphere. Measured on the real cases
  (``reports/segmentation.md``): said on every case whose label reaches
  more than 5 mm into the other hemisphere (BraTS pat0003 FLAIR, 12-14 mL
  there, nearly all missed; the algoseg FLAIR and T2, about 2 mL) and on
  two whose mask is wrong at the midline (pat0003 T1c, the clinical
  brain2 T1c); never on a lateral tumour. On FLAIR, step 3d of
  :mod:`tumor3d.segmentation.lesion` now takes the deep crossing back in part (native
  pat0003: 7.3 of those 12.4 mL, was 0.3; the algoseg FLAIR 1.2 of 2.1 mL,
  was 0.2), so the caveat still holds there: a part may be missing.
  It is shown and does not make the status ``check``
  (:data:`tumor3d.segmentation.review.INFORMING_CAVEATS`): out of fold it
  named bad and good volumes alike, and the masks it named were seldom
  short.
- **The lesion was found without the symmetry rule's confirmation**
  (robust method, FLAIR). A lesion centred on the midline leaves the
  symmetry rule no asymmetric seed; step 3f of :mod:`tumor3d.segmentation.lesion` then
  finds it by its brightness and depth alone, without the evidence that
  tells a tumour from bilateral normal tissue (``LesionResult.midline``).
  The run says so, with the share of the mask that is its own mirror image,
  in place of the midline caveat (the lesion straddles the plane: no part
  of it lies in a hemisphere it does not reach). Measured share
  (``reports/segmentation.md``): 0.71-0.82 on spheres implanted on the
  midline; 0.00-0.12 on every real tumour of ``../shared/data``, none of
  which step 3f found.

- **The tumour comes near the air outside the head** (a raw head, its
  brain found by skull removal). Every brain voxel lies at least the
  thinnest scalp plus skull (:data:`tumor3d.imaging.brain_extraction.
  SCALP_SKULL_MIN_MM`, 5 mm) inside the head's surface, so tumour voxels
  nearer the air are scalp that the brain mask kept and the lesion grew
  into (scalp fat and marrow are bright on FLAIR and T1). The air is
  given only where the volume shows a head around the brain
  (:func:`tumor3d.imaging.brain_extraction.head_around_brain`). Measured
  (``reports/segmentation.md``): the raw TCGA FLAIR, whose mask keeps the
  scalp on its top slices, has 3.52 mL of tumour within 5 mm of the air on
  slices 14-15 and 19-22; every phantom's tumour lies 14-35 mm from it;
  the raw TCGA T2's lesion 10.8 mm.

Slice numbers are 0-based array indices (``slice_index`` of the run's
``slices.parquet``).

The functions are pure: masks in, sentences out.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from tumor3d.errors import InputError
from tumor3d.imaging.brain_extraction import SCALP_SKULL_MIN_MM
from tumor3d.segmentation.lesion import (
    LESION_DEFAULTS,
    SYMMETRY_TOLERANCE_MM,
    MirrorPlane,
    area_in_pixels,
    mirror_image,
)
from tumor3d.segmentation.review import MIDLINE_CAVEAT_START
from tumor3d.validation import check_binary_mask

__all__ = [
    "midline_caveat",
    "scalp_caveat",
    "scan_end_caveat",
    "segmentation_caveats",
    "symmetric_caveat",
]


def _mask3d(tumor_mask: np.ndarray) -> np.ndarray:
    return check_binary_mask(tumor_mask, "tumor_mask", ndim=3)


def _slice_runs(slices: np.ndarray) -> str:
    """Sorted slice indices as runs: ``[3, 4, 5, 9]`` -> ``"3-5, 9"``."""
    zs = [int(z) for z in np.unique(slices)]
    runs: list[list[int]] = []
    for z in zs:
        if runs and z == runs[-1][1] + 1:
            runs[-1][1] = z
        else:
            runs.append([z, z])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)


def scan_end_caveat(tumor_mask: np.ndarray) -> str | None:
    """The caveat for tumour on the scan's first or last slice, else None.

    Parameters
    ----------
    tumor_mask : (z, y, x) array_like of bool
        The segmentation, slices in acquisition order.

    Examples
    --------
    >>> m = np.zeros((4, 3, 3), bool)
    >>> scan_end_caveat(m) is None
    True
    >>> m[3, 1, 1] = True
    >>> scan_end_caveat(m)[:57]
    'tumour on the last slice of the scan (slice 3, 0-based): '
    """
    m = _mask3d(tumor_mask)
    last = m.shape[0] - 1
    first_has, last_has = bool(m[0].any()), bool(m[last].any())
    if last == 0 or not last_has:
        where = "first slice of the scan (slice 0, 0-based)" if first_has else None
    elif first_has:
        where = f"first and last slices of the scan (slices 0 and {last}, 0-based)"
    else:
        where = f"last slice of the scan (slice {last}, 0-based)"
    if where is None:
        return None
    return (
        f"tumour on the {where}: it may continue beyond the scanned range, so every "
        "volume may underestimate it"
    )


def midline_caveat(
    tumor_mask: np.ndarray,
    plane: MirrorPlane,
    spacing_mm: tuple[float, float, float],
    *,
    min_region_mm2: float,
    min_slices: int,
) -> str | None:
    """The caveat for a tumour reaching the mid-sagittal plane, else None.

    The band is the voxels within ``SYMMETRY_TOLERANCE_MM / 2`` of
    ``plane``; the caveat is said when the mask holds at least
    ``min_region_mm2`` of band area on each of ``min_slices`` consecutive
    slices (the lesion model's significance rule, with its pixel count on
    pixels coarser than 1 mm: :func:`tumor3d.segmentation.lesion.area_in_pixels`).

    Parameters
    ----------
    tumor_mask : (z, y, x) array_like of bool
        The segmentation.
    plane : MirrorPlane
        The mid-sagittal plane the symmetry rule used, in the mask's pixel
        frame (``LesionResult.plane``).
    spacing_mm : (3,) tuple of float
        ``(slice step, row, column)`` in mm.
    min_region_mm2 : float
        The significance rule's area, mm2 (``detect.lesion`` of the
        configuration).
    min_slices : int
        Its consecutive slices.
    """
    m = _mask3d(tumor_mask)
    if not m.any():
        return None
    band = np.abs(plane.signed_distance_mm(m.shape[1:], spacing_mm[1:])) <= (
        0.5 * SYMMETRY_TOLERANCE_MM
    )
    per_slice = np.count_nonzero(m & band[np.newaxis], axis=(1, 2))
    need = area_in_pixels(min_region_mm2, float(spacing_mm[1]) * float(spacing_mm[2]))
    big = np.concatenate([[False], per_slice >= need, [False]])
    # runs of consecutive slices with a big cross-section: (start, stop) pairs
    edges = np.flatnonzero(np.diff(big.astype(np.int8)))
    runs = [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]
    runs = [r for r in runs if r[1] - r[0] >= int(min_slices)]
    if not runs:
        return None
    zs = np.concatenate([np.arange(a, b) for a, b in runs])
    plural = "s" if zs.size > 1 else ""
    return (
        f"{MIDLINE_CAVEAT_START} on slice{plural} {_slice_runs(zs)} (0-based, within "
        f"{0.5 * SYMMETRY_TOLERANCE_MM:g} mm of the mid-sagittal plane): the symmetry rule "
        "cannot tell a tumour that crosses the midline from a bilateral normal structure, "
        "so a part in the other hemisphere may be missing (look at those slices in "
        "overlay_tumor.png)"
    )


def symmetric_caveat(
    tumor_mask: np.ndarray, plane: MirrorPlane, spacing_mm: tuple[float, float, float]
) -> str | None:
    """The caveat for a lesion found by step 3f (no asymmetry confirmed it); None if empty.

    It names the share of the mask's voxels whose mirror image (nearest
    pixel, about ``plane``) is in the mask.

    Parameters
    ----------
    tumor_mask : (z, y, x) array_like of bool
        The segmentation.
    plane : MirrorPlane
        The mid-sagittal plane the symmetry rule used, in the mask's pixel frame.
    spacing_mm : (3,) tuple of float
        ``(slice step, row, column)`` in mm.
    """
    m = _mask3d(tumor_mask)
    n = int(np.count_nonzero(m))
    if n == 0:
        return None
    share = np.count_nonzero(m & mirror_image(m, plane, spacing_mm)) / n
    return (
        f"tumour straddles the brain's midline and is {100.0 * share:.0f} % its own mirror "
        "image: the symmetry rule, which tells a tumour from bilateral normal tissue, could "
        "not confirm it, and it was found by its brightness and depth alone (check in "
        "overlay_tumor.png that it is a lesion and not normal tissue)"
    )


def scalp_caveat(
    tumor_mask: np.ndarray,
    head_exterior: np.ndarray,
    spacing_mm: tuple[float, float, float],
) -> str | None:
    """The caveat for tumour within the scalp and skull's thickness of the air, else None.

    Parameters
    ----------
    tumor_mask : (z, y, x) array_like of bool
        The segmentation.
    head_exterior : (z, y, x) array_like of bool
        The air outside the head (``PreprocessResult.head_exterior``).
    spacing_mm : (3,) tuple of float
        ``(slice step, row, column)`` in mm; the distance is in-plane.

    Examples
    --------
    >>> air = np.zeros((2, 20, 20), bool); air[:, :, :2] = True
    >>> m = np.zeros((2, 20, 20), bool); m[1, 8:12, 4:8] = True  # 2 mm from the air
    >>> scalp_caveat(m, air, (5.0, 1.0, 1.0))[:60]
    'tumour within 5 mm of the air outside the head on slice 1 (0'
    >>> m[1, :, :] = False; m[1, 8:12, 10:14] = True  # 8 mm away
    >>> scalp_caveat(m, air, (5.0, 1.0, 1.0)) is None
    True
    """
    m = _mask3d(tumor_mask)
    ext = check_binary_mask(head_exterior, "head_exterior", ndim=3)
    if ext.shape != m.shape:
        raise InputError(f"head_exterior {ext.shape} and tumor_mask {m.shape} differ in shape")
    pixel_mm = (float(spacing_mm[1]), float(spacing_mm[2]))
    near = np.zeros(m.shape, dtype=bool)
    for z in np.flatnonzero(m.any(axis=(1, 2)) & ext.any(axis=(1, 2))):
        dist = ndi.distance_transform_edt(~ext[z], sampling=pixel_mm)
        near[z] = m[z] & (dist < SCALP_SKULL_MIN_MM)
    if not near.any():
        return None
    zs = np.flatnonzero(near.any(axis=(1, 2)))
    ml = np.count_nonzero(near) * float(np.prod(spacing_mm)) / 1000.0
    plural = "s" if zs.size > 1 else ""
    return (
        f"tumour within {SCALP_SKULL_MIN_MM:g} mm of the air outside the head on slice{plural} "
        f"{_slice_runs(zs)} (0-based; {ml:.2f} mL of it): the brain lies deeper than the "
        "scalp and skull, so the brain mask holds scalp there and the tumour may include "
        "scalp, its volume too high: check overlay_tumor.png and overlay_brain.png, and give "
        "the brain mask (--brain-mask) or set preprocess.brain_extraction: head"
    )


def segmentation_caveats(
    tumor_mask: np.ndarray,
    *,
    plane: MirrorPlane | None = None,
    spacing_mm: tuple[float, float, float] | None = None,
    min_region_mm2: float = float(LESION_DEFAULTS["min_region_mm2"]),
    min_slices: int = int(LESION_DEFAULTS["min_slices"]),
    midline_lesion: bool = False,
    head_exterior: np.ndarray | None = None,
) -> tuple[str, ...]:
    """Every caveat of a segmentation, in a fixed order (ends, midline, scalp).

    ``head_exterior`` (the air outside a raw head, ``PreprocessResult.
    head_exterior``) adds :func:`scalp_caveat`; None skips it (a
    skull-stripped volume, a given brain mask).

    ``plane`` is given when the symmetry rule shaped the mask (robust
    method); None skips the midline caveats. ``midline_lesion`` (the lesion
    model's ``LesionResult.midline``: step 3f found it) says
    :func:`symmetric_caveat` in place of :func:`midline_caveat`.
    ``spacing_mm`` None means 1 mm voxels. The significance rule defaults to
    the lesion model's (:data:`tumor3d.segmentation.lesion.LESION_DEFAULTS`).
    """
    m = _mask3d(tumor_mask)
    sp = (1.0, 1.0, 1.0) if spacing_mm is None else tuple(float(v) for v in spacing_mm)
    out = [scan_end_caveat(m)]
    if plane is not None:
        if midline_lesion:
            out.append(symmetric_caveat(m, plane, sp))
        else:
            out.append(
                midline_caveat(m, plane, sp, min_region_mm2=min_region_mm2, min_slices=min_slices)
            )
    if head_exterior is not None:
        out.append(scalp_caveat(m, head_exterior, sp))
    return tuple(c for c in out if c)
