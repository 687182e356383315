"""Brain extraction from a raw (not skull-stripped) head, in millimetres.

:func:`extract_brain` finds the brain in a ``(z, y, x)`` 8-bit head volume
whose scalp, skull, face and neck are still present. It replaces the
per-slice "Otsu, 2-pixel opening, largest component" of
:func:`tumor3d.imaging.preprocess.remove_skull` [A3] where that recipe keeps the
whole head (scalp fat and skull marrow joined to the brain by thin bright
bridges through the skull). Every size is anatomical and in mm, so the same
constants work from 0.8 mm to 4 mm pixels and from 1 mm to 7 mm slices.

Method (no training data; morphological brain extraction in the line of
Brummer et al. 1993, doi:10.1109/42.232249, and the Brain Surface Extractor,
Shattuck et al. 2001, doi:10.1006/nimg.2001.0717, with BET's robust
intensity range, Smith 2002, doi:10.1002/hbm.10062):

1. **Soft tissue** ``B = I > t``, ``t`` the lower of the two 3-class Otsu
   thresholds of the volume: it separates air, bone (and CSF on T1) from
   all soft tissue.
2. **Working grid** of about ``_GRID_MM`` per voxel: blocks of voxels, a
   block being tissue only if *all* its voxels are, so a dark skull line
   one pixel wide still separates blocks (the grid never bridges the
   skull) and the morphology below costs the same at any resolution.
3. **Head depth** ``d_h``: 3-D Euclidean distance in mm from every voxel of
   the head (tissue with each slice's holes filled, so the scalp ring
   encloses skull and brain; largest 3-D component) to the outside of the head, the volume's
   first and last slices counting as bordered by air.
4. **Brain intensity range** from the deep head (``d_h > _DEEP_MM``), which
   above the skull base is brain only: median ``m`` and robust standard
   deviation ``s = 1.4826 MAD``; brain tissue is ``[m - k s, m + k s]``,
   ``k = _RANGE_SIGMAS``. In the outer ``_SHELL_MM`` of the head (scalp and
   skull: where fat and marrow are) voxels above that range are excluded,
   which cuts the bright bridges; deeper, bright voxels (CSF on T2,
   enhancing or FLAIR-bright tumour) are kept.
5. **Core**: the candidate of step 4 eroded by a ball of ``_EROSION_MM``
   (3-D distance in mm, anisotropic sampling) and restricted to
   ``d_h > _EROSION_MM + SCALP_SKULL_MIN_MM`` (no brain voxel lies
   shallower than the thinnest scalp plus skull, so no core voxel of the
   brain lies shallower than that plus the erosion). Of its 6-connected
   components the one holding most deep voxels is the brain's (rather
   than "the largest", which can be the face or neck).
6. **Reconstruction**: geodesic dilation of the core *within* the tissue
   (a path may not cross the dark skull) by ``ceil(_EROSION_MM / grid)``
   steps of the in-plane 3x3 square (plus the neighbouring slices where the
   slice step is at most 1.5 grid voxels): this restores the eroded rim.
   Back on the full-resolution grid (intersected with ``B``) it is dilated
   in-plane, within ``B``, by one grid voxel, so the border is the
   full-resolution tissue boundary and a dark line one pixel wide is never
   crossed.
7. The holes of every slice are filled (ventricles, dark necrosis, vessels).

Not for skull-stripped input: there the head surface *is* the brain
surface, the depth restriction of step 5 keeps the core 10 mm inside it
and step 6 restores only 5 mm, so a rim of about 5 mm is lost
(:func:`tumor3d.imaging.preprocess.foreground_brain_mask` is the path for such
volumes).

Known weaknesses (measured, see ``benchmarks/brain_extraction_eval.py``):
on thick slices there is no growth across slices, so the brain's first and
last slices (where the cross-section is small and near the head surface)
are often lost; a rim of about 1-2 mm is lost where a bright CSF rim (T2)
is excluded by the intensity range; at the skull base the face and
temporal muscle can still be joined through the orbits; the robust range
is global, so a strong bias field can push part of the brain below it.

The mask is the brain *tissue*: on T1 the dark sulcal and peripheral CSF
outside the brain's slice outline stays out, as it does in ``remove_skull``.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage as ndi
from skimage.filters import threshold_multiotsu

from tumor3d.errors import InputError

__all__ = [
    "HEAD_CLOSING_MM",
    "SCALP_SKULL_MIN_MM",
    "extract_brain",
    "head_around_brain",
    "head_exterior",
    "soft_tissue_threshold",
]

#: Working grid (mm). Half the thinnest skull (about 4 mm at the temporal
#: squama together with its dark periosteum/dura) and well below the
#: erosion radius, so the morphology is not coarser than the anatomy it
#: separates; pixels larger than this are used as they are.
_GRID_MM = 2.0

#: Erosion radius (mm). Scalp-brain bridges through the skull (emissary
#: veins, partial-volume voxels of a thin or obliquely cut skull, marrow)
#: are a few mm wide, so an erosion by 5 mm (a 10 mm wide cut) breaks them,
#: while the cerebral hemispheres, cerebellum and brainstem (>= 20 mm
#: thick) keep a connected core.
_EROSION_MM = 5.0

#: Thinnest scalp plus skull (mm): adult scalp is 3-8 mm and the skull
#: 2-10 mm thick, so every brain voxel lies at least about 5 mm under the
#: head surface.
SCALP_SKULL_MIN_MM = 5.0

#: Outer shell of the head holding scalp fat and skull marrow (mm): scalp
#: (<= 8 mm) plus skull (<= 10 mm) plus a margin; bright voxels are only
#: excluded there.
_SHELL_MM = 20.0

#: Depth beyond which the head is brain above the skull base (mm): deeper
#: than the thickest scalp + skull + CSF rim (about 20 mm) by a margin. On a
#: small head (maximum depth < 60 mm) half the maximum depth is used.
_DEEP_MM = 30.0

#: Half width of the brain intensity range in robust standard deviations.
#: Grey and white matter of the deep head form one mode (plus a minority of
#: CSF and lesion); 4 standard deviations hold 99.99 % of a normal mode, so
#: only a different tissue (fat, marrow, enhancing vessels on T1) falls
#: outside it.
_RANGE_SIGMAS = 4.0

#: Scale factor from the median absolute deviation to the standard
#: deviation of a normal distribution.
_MAD_TO_SD = 1.4826

_IN_PLANE = np.zeros((3, 3, 3), dtype=bool)
_IN_PLANE[1] = ndi.generate_binary_structure(2, 1)
_SQUARE = np.zeros((3, 3, 3), dtype=bool)
_SQUARE[1] = True


def extract_brain(image_u8: np.ndarray, spacing_mm: tuple[float, float, float]) -> np.ndarray:
    """Brain mask of a raw head volume (scalp, skull, face still present).

    See the module docstring for the method and the anatomical reason of
    every constant.

    Parameters
    ----------
    image_u8 : (z, y, x) ndarray of uint8
        The windowed volume (``PreprocessResult.original_u8``); not modified.
    spacing_mm : (float, float, float)
        ``(slice step, row, column)`` spacing in mm, each > 0.

    Returns
    -------
    (z, y, x) ndarray of bool
        The brain. Empty if the volume is constant or holds no soft tissue
        body thicker than the erosion ball (nothing that can be a brain).

    Raises
    ------
    InputError
        If ``image_u8`` is not a non-empty 3-D uint8 array or ``spacing_mm``
        is not three positive finite numbers.

    Examples
    --------
    A 60 mm ball of tissue (brain, 100) in a 6 mm dark skull (10) in a 6 mm
    bright scalp (200), joined to the scalp by a bright 3 mm bridge, on a
    2 mm grid:

    >>> z, y, x = np.mgrid[-50:51:2, -50:51:2, -50:51:2]
    >>> r = np.sqrt(x**2 + y**2 + z**2)
    >>> head = np.where(r < 36, 100, np.where(r < 42, 10, np.where(r < 48, 200, 0)))
    >>> head[(np.abs(y) < 2) & (np.abs(z) < 2) & (x > 0) & (r < 48)] = 200
    >>> mask = extract_brain(head.astype(np.uint8), (2.0, 2.0, 2.0))
    >>> bool(mask[25, 25, 25])  # the centre
    True
    >>> bool(mask[25, 25, 46:].any())  # the scalp at the bridge
    False
    >>> round(2 * int((mask & (r < 36)).sum()) / (int(mask.sum()) + int((r < 36).sum())), 2)
    1.0
    """
    image, spacing = _check_inputs(image_u8, spacing_mm)
    return _extract_brain(image, spacing)


def _check_inputs(image_u8: object, spacing_mm: object) -> tuple[np.ndarray, np.ndarray]:
    image = np.asarray(image_u8)
    if image.ndim != 3:
        raise InputError(
            f"extract_brain needs a 3-D (z, y, x) volume, got {image.ndim} dimension(s)"
        )
    if image.dtype != np.uint8:
        raise InputError(
            f"extract_brain needs a uint8 volume (see tumor3d.imaging.preprocess.to_uint8), "
            f"got dtype {image.dtype}"
        )
    if min(image.shape) == 0:
        raise InputError(f"extract_brain got an empty volume (shape {image.shape})")
    try:
        spacing = np.array([float(s) for s in spacing_mm], dtype=np.float64)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise InputError(
            f"spacing_mm must be three numbers (slice step, row, column) in mm, got {spacing_mm!r}"
        ) from None
    if spacing.shape != (3,) or not np.all(np.isfinite(spacing)) or not np.all(spacing > 0):
        raise InputError(
            f"spacing_mm must be three positive finite numbers (slice step, row, column) "
            f"in mm, got {spacing_mm!r}"
        )
    return image, spacing


def soft_tissue_threshold(image: np.ndarray) -> int | None:
    """Step 1's gray level: soft tissue is ``image > t``; None with one gray level only.

    ``t`` is the lower of the two 3-class Otsu thresholds of the 8-bit
    volume, which separates air and bone (and CSF on T1) from soft tissue;
    with only two gray levels, the brighter one is tissue.
    """
    hist = np.bincount(np.asarray(image, dtype=np.uint8).ravel(), minlength=256)
    levels = np.flatnonzero(hist)
    if levels.size < 2:
        return None
    return int(threshold_multiotsu(hist=hist, classes=3)[0]) if levels.size >= 3 else int(levels[0])


#: Gaps (mm) in the scalp's ring that the head's outline bridges (:func:`head_exterior`):
#: a dark pixel or two of noise, or of a thin scalp cut obliquely; the skull inside
#: is thicker than this and is no gap (the outline is filled inside).
HEAD_CLOSING_MM = 3.0


def head_exterior(
    image: np.ndarray, pixel_spacing_mm: tuple[float, float] = (1.0, 1.0)
) -> np.ndarray:
    """The air outside a raw head, slice by slice: the complement of the head's outline.

    The head is the soft tissue (:func:`soft_tissue_threshold`) of a slice,
    closed with a disk of :data:`HEAD_CLOSING_MM` (a small gap in the scalp
    would let the dark skull and CSF inside count as air) and its holes
    filled (skull, CSF and brain inside); the air is the rest. A slice whose
    tissue touches the image border (a head cut by the field of view) has no
    closed outline: it gets no air (all False), so nothing is said there. A
    slice without tissue is air throughout. Meaningless for a volume of the
    brain alone (skull-stripped): see :func:`head_around_brain`.

    Parameters
    ----------
    image : (z, y, x) ndarray of uint8
        The original 8-bit slices (``PreprocessResult.original_u8``).
    pixel_spacing_mm : (2,) tuple of float
        Row and column spacing, mm.

    Returns
    -------
    (z, y, x) ndarray of bool
        All False when the volume holds one gray level only.

    Examples
    --------
    >>> head = np.zeros((1, 11, 11), np.uint8)
    >>> head[0, 1:10, 1:10] = 200  # scalp
    >>> head[0, 2:9, 2:9] = 10     # dark skull
    >>> head[0, 3:8, 3:8] = 120    # brain
    >>> head[0, 1, 5] = 0          # a one-pixel gap in the scalp
    >>> ext = head_exterior(head)  # the corner is air; the skull behind the gap is not
    >>> bool(ext[0, 0, 0]), bool(ext[0, 2, 5]), bool(ext[0, 5, 5])
    (True, False, False)
    """
    from skimage.morphology import disk

    img = np.asarray(image)
    t = soft_tissue_threshold(img)
    out = np.zeros(img.shape, dtype=bool)
    if t is None:
        return out
    radius = max(1, int(round(HEAD_CLOSING_MM / min(float(v) for v in pixel_spacing_mm))))
    footprint = disk(radius)
    for z in range(img.shape[0]):
        tissue = img[z] > t
        if not tissue.any():
            out[z] = True
            continue
        if tissue[0].any() or tissue[-1].any() or tissue[:, 0].any() or tissue[:, -1].any():
            continue  # cut by the field of view: no closed outline
        padded = np.pad(tissue, radius)
        closed = ndi.binary_closing(padded, structure=footprint)[radius:-radius, radius:-radius]
        out[z] = ~ndi.binary_fill_holes(closed)
    return out


def head_around_brain(
    brain: np.ndarray, exterior: np.ndarray, pixel_spacing_mm: tuple[float, float]
) -> bool:
    """Whether the volume shows a head around the brain (scalp and skull), not the brain alone.

    On the brain's large slices (area at least half its largest), the median
    in-plane distance from the brain mask's boundary to the air
    (:func:`head_exterior`) is at least :data:`SCALP_SKULL_MIN_MM`: a head's
    brain lies under its scalp and skull. A volume of the brain alone whose
    background is not one constant value (noise, a resampling) has its air
    right at the brain; so does a brain mask that kept the whole head on
    every slice (the brain-volume note says that one). Measured (median on
    those slices): 11-26 mm on the raw TCGA heads, over 10 mm on the phantoms'
    heads; 1 mm where the mask is the whole head (``thick_t1c_brain2``).
    """
    b = np.asarray(brain, dtype=bool)
    ext = np.asarray(exterior, dtype=bool)
    area = np.count_nonzero(b, axis=(1, 2))
    if area.max(initial=0) == 0:
        return False
    medians = []
    for z in np.flatnonzero(area >= 0.5 * area.max()):
        if not ext[z].any():
            continue  # no closed outline there
        edge = b[z] & ~ndi.binary_erosion(b[z])
        dist = ndi.distance_transform_edt(~ext[z], sampling=pixel_spacing_mm)
        medians.append(float(np.median(dist[edge])))
    return bool(medians) and float(np.median(medians)) >= SCALP_SKULL_MIN_MM


def _extract_brain(image: np.ndarray, spacing: np.ndarray) -> np.ndarray:
    empty = np.zeros(image.shape, dtype=bool)
    # step 1: soft tissue. With only 2 gray levels, the brighter one is tissue.
    t = soft_tissue_threshold(image)
    if t is None:
        return empty
    tissue = image > t

    # step 2: working grid of blocks of about _GRID_MM
    factor = np.clip(np.floor(_GRID_MM / spacing + 1e-9).astype(int), 1, image.shape)
    grid_mm = spacing * factor
    tissue_g = _block_all(tissue, factor)

    # step 3: the head and its depth (the end slices border air)
    # (slice by slice the scalp ring encloses skull and brain; then the largest body)
    head = _largest_component(_fill_holes_per_slice(tissue_g))
    if not head.any():
        return empty
    depth = ndi.distance_transform_edt(np.pad(head, ((1, 1), (0, 0), (0, 0))), sampling=grid_mm)
    depth = depth[1:-1]

    # step 4: brain intensity range from the deep head
    deep = tissue_g & (depth > min(_DEEP_MM, 0.5 * float(depth.max())))
    sample = image[tuple(slice(0, n * k, k) for n, k in zip(tissue_g.shape, factor, strict=True))]
    values = sample[deep].astype(np.float64)
    if values.size == 0:
        return empty
    centre = float(np.median(values))
    sd = _MAD_TO_SD * float(np.median(np.abs(values - centre)))
    low, high = centre - _RANGE_SIGMAS * sd, centre + _RANGE_SIGMAS * sd
    not_bright = _block_all(image <= high, factor)
    candidate = _block_all(tissue & (image >= low), factor) & (not_bright | (depth > _SHELL_MM))

    # step 5: the core and the brain's component of it
    core = ndi.distance_transform_edt(candidate, sampling=grid_mm) > _EROSION_MM
    core &= depth > _EROSION_MM + SCALP_SKULL_MIN_MM
    labels, n = ndi.label(core)
    if n == 0:
        return empty
    score = np.bincount(labels[deep], minlength=n + 1)
    score[0] = 0
    if score.max() == 0:  # no component reaches the deep head: take the largest
        score = np.bincount(labels.ravel(), minlength=n + 1)
        score[0] = 0
    core = labels == int(np.argmax(score))

    # step 6: reconstruction within the tissue, then back to full resolution
    step = _SQUARE.copy()
    if grid_mm[0] <= 1.5 * grid_mm[1:].max():  # slices close enough to grow across
        step[0, 1, 1] = step[2, 1, 1] = True
    n_steps = int(np.ceil(_EROSION_MM / float(grid_mm[1:].min())))
    brain_g = ndi.binary_dilation(core, structure=step, iterations=n_steps, mask=tissue_g)
    # blocks only partly tissue are not in tissue_g: a geodesic in-plane dilation by
    # one block at full resolution reaches the border without crossing a dark line
    brain = tissue & _upsample(brain_g, factor, image.shape)
    box = _bounding_box(brain, pad=factor)
    if box is None:
        return empty
    n_steps = int(factor[1:].max())
    if n_steps > 1:
        brain[box] = ndi.binary_dilation(
            brain[box], structure=_IN_PLANE, iterations=n_steps - 1, mask=tissue[box]
        )

    # step 7
    return _fill_holes_per_slice(brain)


def _bounding_box(mask: np.ndarray, pad: np.ndarray) -> tuple[slice, ...] | None:
    """Slices of the bounding box of ``mask``, widened by ``pad`` voxels per axis."""
    if not mask.any():
        return None
    box = []
    for axis, (n, p) in enumerate(zip(mask.shape, pad, strict=True)):
        hit = np.flatnonzero(mask.any(axis=tuple(a for a in range(3) if a != axis)))
        box.append(slice(max(0, int(hit[0]) - int(p)), min(n, int(hit[-1]) + int(p) + 1)))
    return tuple(box)


def _block_all(mask: np.ndarray, factor: np.ndarray) -> np.ndarray:
    """``True`` where every voxel of a ``factor`` block is; the remainder is dropped."""
    nz, ny, nx = (n // k for n, k in zip(mask.shape, factor, strict=True))
    fz, fy, fx = (int(k) for k in factor)
    if (fz, fy, fx) == (1, 1, 1):
        return mask.copy()
    cropped = mask[: nz * fz, : ny * fy, : nx * fx]
    return cropped.reshape(nz, fz, ny, fy, nx, fx).all(axis=(1, 3, 5))


def _upsample(mask: np.ndarray, factor: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """Nearest-block upsampling to ``shape``; the remainder repeats the last block."""
    index = [
        np.minimum(np.arange(n) // k, m - 1)
        for n, k, m in zip(shape, factor, mask.shape, strict=True)
    ]
    return mask[np.ix_(*index)]


def _largest_component(mask: np.ndarray) -> np.ndarray:
    labels, n = ndi.label(mask)
    if n <= 1:
        return labels > 0
    sizes = np.bincount(labels.ravel())
    sizes[0] = 0
    return labels == int(np.argmax(sizes))


def _fill_holes_per_slice(mask: np.ndarray) -> np.ndarray:
    padded = np.pad(mask, ((1, 1), (0, 0), (0, 0)))
    return ndi.binary_fill_holes(padded, structure=_IN_PLANE)[1:-1]
