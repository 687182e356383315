"""The lesion model's lengths (mm) and areas (mm2) in pixels of a scan.

See the closing paragraphs of :mod:`tumor3d.segmentation.lesion`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tumor3d.segmentation.lesion.growth import LOCAL_SIGMA_MM

#: Pixel area (mm2) on which the model's areas were chosen (BraTS, 1 mm pixels): finer
#: pixels keep the area, coarser ones the pixel count (see area_in_pixels).
REFERENCE_PIXEL_MM2 = 1.0


def _blur_reach(smoothing_px: float) -> int:
    """The blur's reach in pixels: 2 sigma of the step-1 Gaussian, at least 1."""
    return max(1, int(round(2 * float(smoothing_px))))


def area_in_pixels(area_mm2: float, pixel_mm2: float) -> int:
    """The pixel count a significance rule of ``area_mm2`` needs on pixels of ``pixel_mm2``.

    The area itself on pixels of ``REFERENCE_PIXEL_MM2`` (1 mm) or finer: the same
    anatomy, more samples. On coarser pixels the count the rule has at 1 mm: an area
    decided by a few coarse pixels is decided by a few noisy samples (measured: on the
    4 mm pixels of the tumour-free ``aniso_vox`` volume a 50 mm2 rule, 3 pixels, reports
    1.7 mL of false lesion; ``reports/segmentation.md``), so below 1 mm the rule is an
    area and above it a number of samples. At least 1.

    >>> area_in_pixels(50.0, 0.25), area_in_pixels(50.0, 1.0), area_in_pixels(50.0, 16.0)
    (200, 50, 50)
    """
    return max(1, int(round(float(area_mm2) / min(float(pixel_mm2), REFERENCE_PIXEL_MM2))))


@dataclass(frozen=True)
class _PixelLengths:
    """The model's in-plane lengths and areas in pixels (:func:`_pixel_lengths`)."""

    smoothing: float  # step 1's Gaussian sigma
    min_region: int  # a significant cross-section
    rings: int  # step 4's rings of local growth
    local_sigma: float  # the Gaussian of the rings' local lesion gray


def _pixel_lengths(
    voxel_mm: tuple[float, ...], smoothing_mm: float, min_region_mm2: float, boundary_mm: float
) -> _PixelLengths:
    """Pixels for the model's lengths (mm) and areas (mm2), through the in-plane spacing.

    The pixel's side is the geometric mean of the row and column spacings (the
    side of a square pixel of the same area; an in-plane anisotropy of a few per
    cent, as on real scanners, is not modelled by the isotropic filters). At
    1 mm pixels each value is the one given. The significant area is
    :func:`area_in_pixels` (an area on pixels of 1 mm or finer, a pixel count
    on coarser ones).

    >>> _pixel_lengths((5.0, 0.5, 0.5), 2.0, 50.0, 3.0)
    _PixelLengths(smoothing=4.0, min_region=200, rings=6, local_sigma=6.0)
    """
    side = float(np.sqrt(float(voxel_mm[1]) * float(voxel_mm[2])))
    return _PixelLengths(
        smoothing=float(smoothing_mm) / side,
        min_region=area_in_pixels(min_region_mm2, side**2),
        rings=int(round(float(boundary_mm) / side)),
        local_sigma=LOCAL_SIGMA_MM / side,
    )
