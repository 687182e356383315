"""Mask geometry shared by the steps of :mod:`tumor3d.segmentation.lesion`.

Connected components (26-connected in 3-D), the significant seed components
of step 3, in-plane dilations and distances, and bounding boxes.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi


def _significant_components(
    seeds: np.ndarray, min_region_pixels: int, min_slices: int
) -> tuple[np.ndarray, np.ndarray]:
    """Label 26-connected seed components; return labels and the significant ids by size."""
    labels, n = ndi.label(seeds, structure=np.ones((3, 3, 3), dtype=bool))
    if n == 0:
        return labels, np.zeros(0, dtype=np.int64)
    nz = seeds.shape[0]
    zz = np.broadcast_to(np.arange(nz)[:, None, None], seeds.shape)[seeds]
    ll = labels[seeds]
    per_slice = np.bincount(ll * nz + zz, minlength=(n + 1) * nz).reshape(n + 1, nz)
    big = per_slice >= int(min_region_pixels)
    # longest run of consecutive slices with a big cross-section
    run = np.zeros(n + 1, dtype=np.int64)
    cur = np.zeros(n + 1, dtype=np.int64)
    for z in range(nz):
        cur = np.where(big[:, z], cur + 1, 0)
        run = np.maximum(run, cur)
    ok = np.flatnonzero(run >= int(min_slices))
    ok = ok[ok > 0]
    sizes = per_slice.sum(axis=1)
    return labels, ok[np.argsort(-sizes[ok], kind="stable")]


def _box_dilate(mask: np.ndarray, half_y: int, half_x: int) -> np.ndarray:
    """In-plane dilation by a ``(2 half_y + 1) x (2 half_x + 1)`` box (separable, fast).

    Equal to ``half`` iterations of a 3 x 3 binary dilation when both halves agree.
    """
    size = (1, 2 * int(half_y) + 1, 2 * int(half_x) + 1)
    grown = ndi.maximum_filter(mask.view(np.uint8), size=size, mode="constant", cval=0)
    return grown > 0


def _touching(cand: np.ndarray, seed: np.ndarray) -> np.ndarray:
    """The 26-connected components of ``cand`` that hold a voxel of ``seed``."""
    lab, _ = ndi.label(cand, structure=np.ones((3, 3, 3), dtype=bool))
    keep = np.unique(lab[seed])
    return np.isin(lab, keep[keep > 0])


def _within_mm(mask: np.ndarray, radius_mm: float, voxel_mm) -> np.ndarray:
    """In-plane: voxels within ``radius_mm`` of ``mask`` (per slice, Euclidean)."""
    out = np.zeros_like(mask)
    for z in np.flatnonzero(mask.any(axis=(1, 2))):
        d = ndi.distance_transform_edt(~mask[z], sampling=(voxel_mm[1], voxel_mm[2]))
        out[z] = d <= radius_mm
    return out


def _bounding_box(b: np.ndarray, pad: int) -> tuple[slice, ...]:
    out = [slice(None)]
    for axis in (1, 2):
        idx = np.flatnonzero(b.any(axis=tuple(a for a in (0, 1, 2) if a != axis)))
        out.append(slice(max(idx[0] - pad, 0), min(idx[-1] + pad + 1, b.shape[axis])))
    return tuple(out)


def _widened_box(mask: np.ndarray, pad: tuple[int, int, int]) -> tuple[slice, ...]:
    """The bounding box of a non-empty 3-D ``mask``, widened by ``pad`` voxels per axis."""
    box = []
    for ax in range(3):
        idx = np.flatnonzero(mask.any(axis=tuple(a for a in range(3) if a != ax)))
        box.append(slice(max(idx[0] - pad[ax], 0), idx[-1] + pad[ax] + 1))
    return tuple(box)
