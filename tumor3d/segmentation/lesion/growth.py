"""Step 4 and step 4b: the lesion around its seeds, by the partial-volume rule.

The refinement of a seed core (:func:`_refine`), the boundary rings grown
against the local lesion gray (:func:`_grow_local`) and the satellites the
refined lesion reaches (:func:`_reached`); see steps 4 and 4b of
:mod:`tumor3d.segmentation.lesion`.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi

from tumor3d.segmentation.lesion.normal import NormalModel
from tumor3d.segmentation.lesion.regions import _bounding_box, _box_dilate, _touching, _widened_box

#: Step 4: Gaussian sigma (mm, in-plane) and truncation (sigmas) of the local lesion gray
#: of the boundary rings (_grow_local); the box the growth works on follows from both.
LOCAL_SIGMA_MM = 3.0


LOCAL_TRUNCATE = 4.0


#: Step 4b: on FLAIR and T2 a satellite within this distance (mm, in 3-D through the voxel
#: spacing) of the refined lesion joins it. Foci less than 1 cm apart are read as one
#: tumour: "multiple" glioblastomas are those whose lesions lie at least 1 cm apart (Singh
#: et al., Asian J Neurosurg 2015). Not on T1c, where normal enhancing structures (vessels,
#: dura, choroid plexus) lie next to a tumour. Measured, not fitted: 5 mm joins nothing
#: beyond the touching rule on the labelled cases, 10 and 15 mm join the same pat0005
#: satellite, 20 mm adds a false one on the native T2 (``reports/segmentation.md``).
SATELLITE_MM = 10.0


def _grow_local(
    mask: np.ndarray,
    img: np.ndarray,
    allowed: np.ndarray,
    model: NormalModel,
    floor_sigmas: float,
    rings: int,
    sigma_px: float,
) -> np.ndarray:
    """Partial-volume growth against the *local* lesion intensity, one ring at a time.

    Oedema at the lesion's border is darker than the lesion's median, so the
    global midpoint of step 4 cuts it. A pixel 8-adjacent (in-plane) to the
    mask joins when its gray exceeds ``max(mu + floor_sigmas sigma, (l + mu) / 2)``
    with ``l`` the mean gray of the mask pixels around it (Gaussian weights,
    sigma ``sigma_px``: ``LOCAL_SIGMA_MM`` in pixels): more than half lesion
    by linear partial volume against the lesion tissue next to it, and
    outside the normal model (the floor stops the growth from creeping
    through normal tissue brighter than ``mu``).
    """
    if int(rings) <= 0 or not mask.any():
        return mask
    # work on the mask's in-plane bounding box widened by the rings and the Gaussian's
    # support: every pixel the growth can reach sees the same neighbourhood as in the
    # whole volume (identical result), at a fraction of the cost
    margin = int(rings) + int(LOCAL_TRUNCATE * float(sigma_px) + 0.5) + 1
    zs = np.flatnonzero(mask.any(axis=(1, 2)))  # the growth is in-plane: no z support
    box = (slice(zs[0], zs[-1] + 1), *_bounding_box(mask, margin)[1:])
    out = mask.copy()
    out[box] = _grow_local_box(
        mask[box], img[box], allowed[box], model, floor_sigmas, rings, float(sigma_px)
    )
    return out


def _grow_local_box(mask, img, allowed, model, floor_sigmas, rings, sigma_px):
    """:func:`_grow_local` on a box that holds the whole growth."""
    f = img.astype(np.float32)
    ring_fp = np.ones((1, 3, 3), dtype=bool)
    floor = model.median + float(floor_sigmas) * model.sigma
    for _ in range(int(rings)):
        m32 = mask.astype(np.float32)
        sigma = (0.0, sigma_px, sigma_px)
        num = ndi.gaussian_filter(f * m32, sigma, truncate=LOCAL_TRUNCATE)
        den = ndi.gaussian_filter(m32, sigma, truncate=LOCAL_TRUNCATE)
        local = num / np.maximum(den, 1e-6)
        threshold = np.maximum(floor, 0.5 * (local + model.median))
        ring = ndi.binary_dilation(mask, structure=ring_fp) & ~mask & allowed
        add = ring & (f > threshold)
        if not add.any():
            break
        mask = mask | add
    return mask


def _refine(core, img, allowed, grow_t, reach, tips, model, floor_sigmas, rings, *, local_px):
    """Step 4: the lesion around its seed core, decided by the partial-volume rule.

    ``reach`` (the zone around the core) and ``rings`` are pixels; ``local_px`` is the
    rings' Gaussian (:func:`_grow_local`) in pixels.
    """
    mask = np.zeros_like(core)
    if not core.any():
        return mask
    # everything below happens within the zone, the core's box widened by the zone's reach
    box = _widened_box(core, (1 if tips else 0, reach, reach))
    c = core[box]
    # the lesion may continue onto the slice just beyond its seeds (its tip, too
    # small or too partial-volumed for a seed): the zone reaches one slice further
    zone = ndi.binary_dilation(c, structure=np.ones((3, 1, 1), bool)) if tips else c
    zone = _box_dilate(zone, reach, reach)
    # the smoothed seeds only locate the lesion: every pixel is decided by the
    # partial-volume rule, so the blur halo of the seeds does not stay in
    cand = allowed[box] & zone & (img[box] > grow_t)
    mask[box] = _touching(cand, c)
    if rings > 0 and mask.any():
        mask = _grow_local(mask, img, allowed, model, floor_sigmas, rings, local_px)
    return mask


def _reached(
    satellites: np.ndarray, mask: np.ndarray, reach_mm: float, voxel_mm: tuple[float, ...]
) -> np.ndarray:
    """Step 4b: the satellite components the lesion ``mask`` reaches.

    Those that touch it (26-connected), and with ``reach_mm > 0`` those that
    come within ``reach_mm`` of it (3-D, through ``voxel_mm``).
    """
    out = np.zeros_like(satellites)
    if not (satellites.any() and mask.any()):
        return out
    # everything is decided within the satellites' bounding box widened by the reach (and
    # one voxel, for touching): a mask voxel farther away reaches no satellite voxel
    pad = tuple(int(np.ceil(reach_mm / float(voxel_mm[ax]))) + 1 for ax in range(3))
    box = _widened_box(satellites, pad)
    sat, m = satellites[box], mask[box]
    if not m.any():
        return out
    hit = sat & ndi.binary_dilation(m, structure=np.ones((3, 3, 3), dtype=bool))
    if reach_mm > 0:
        hit |= sat & (ndi.distance_transform_edt(~m, sampling=voxel_mm) <= reach_mm)
    out[box] = _touching(sat, hit)
    return out
