"""Tumour volume estimates and error measures (spec sections 8 and 9).

* :func:`volume_eq7_mm3` -- the paper's slab volume, Eq. 7-8 with [A26]:
  ``V = (gap + thickness) * sum_i N_i * dx * dy`` over the abnormal
  *original* slices;
* :func:`volume_voxel_mm3` -- voxel counting on any grid;
* :func:`voxel_volume_mm3` -- the volume of one voxel of an affine;
* :func:`relative_error_percent` -- Eq. 9, ``|est - truth| / truth * 100``;
* :func:`mm3_to_ml` -- unit conversion;
* :func:`measure_volumes` -- the measure stage: every volume of one patient,
  with the rule of which slices Eq. 7 sums (:data:`EQ7_SLICE_RULES`).

Mesh volume and area are in :mod:`tumor3d.geometry.surface`.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any, Literal

import numpy as np

from tumor3d.errors import InputError
from tumor3d.geometry.mesh import Mesh
from tumor3d.geometry.surface import mesh_volume_mm3

__all__ = [
    "EQ7_SLICE_RULES",
    "VolumeMeasurement",
    "measure_volumes",
    "mm3_to_ml",
    "relative_error_percent",
    "volume_eq7_mm3",
    "volume_voxel_mm3",
    "voxel_volume_mm3",
]


def _positive(value: float, name: str, unit: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InputError(f"{name} must be a number of {unit}, got {value!r}")
    v = float(value)
    if not (math.isfinite(v) and v > 0.0):
        raise InputError(f"{name} must be a positive finite number of {unit}, got {value}")
    return v


def _finite(value: float, name: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InputError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise InputError(f"{name} must be finite, got {value}")
    return v


def volume_eq7_mm3(
    tumor_pixels: np.ndarray,
    abnormal: np.ndarray,
    *,
    pixel_area_mm2: float,
    slab_height_mm: float,
) -> float:
    r"""Tumour volume from per-slice pixel counts, Eq. 7-8 of the paper.

    .. math::

        V = (\text{gap} + \text{thickness}) \sum_{i \in \text{abnormal}} A_i,
        \qquad A_i = N_i \, \Delta x \, \Delta y

    where the sum runs over the *original* (acquired) slices flagged
    abnormal, ``N_i`` is the number of tumour pixels on slice ``i`` and the
    "pixel dimension" of Eq. 8 is the pixel area ([A26]).

    Parameters
    ----------
    tumor_pixels : (n_slices,) array_like of int
        ``N_i`` for every original slice (e.g. ``mask.sum(axis=(1, 2))`` of a
        ``(z, y, x)`` mask). Non-negative integers.
    abnormal : (n_slices,) array_like of bool
        Abnormal-slice flags (section 2); slices not flagged are not counted
        whatever their pixel count.
    pixel_area_mm2 : float
        ``dx * dy`` in mm^2, > 0.
    slab_height_mm : float
        Slice thickness + inter-slice gap in mm, > 0 ([A9]: 5 mm in the paper).

    Returns
    -------
    float
        Volume in mm^3.

    Raises
    ------
    InputError
        On mismatched or non-1-D inputs, negative or non-integer counts,
        non-boolean flags, or non-positive geometry.

    Examples
    --------
    >>> volume_eq7_mm3([10, 20, 30], [False, True, True],
    ...                pixel_area_mm2=0.25, slab_height_mm=5.0)
    62.5
    """
    counts = np.asarray(tumor_pixels)
    flags = np.asarray(abnormal)
    if counts.ndim != 1:
        raise InputError(
            f"tumor_pixels must be 1-D (one count per slice), got shape {counts.shape}"
        )
    if flags.shape != counts.shape:
        raise InputError(
            f"abnormal must have the shape of tumor_pixels {counts.shape}, got {flags.shape}"
        )
    if counts.size and not (
        np.issubdtype(counts.dtype, np.integer)
        or (
            np.issubdtype(counts.dtype, np.floating)
            and np.all(np.isfinite(counts))
            and np.all(counts == np.round(counts))
        )
    ):
        raise InputError("tumor_pixels must hold whole pixel counts (integers)")
    if counts.size and counts.min() < 0:
        raise InputError(f"tumor_pixels must be >= 0, got a minimum of {counts.min()}")
    if flags.dtype != np.bool_:
        raise InputError(f"abnormal must be a boolean array, got dtype {flags.dtype}")
    area = _positive(pixel_area_mm2, "pixel_area_mm2", "mm^2")
    height = _positive(slab_height_mm, "slab_height_mm", "mm")
    n_pixels = int(counts[flags].astype(np.int64).sum())
    return height * n_pixels * area


def volume_voxel_mm3(mask: np.ndarray, *, voxel_volume_mm3: float) -> float:
    """Volume of a binary mask by voxel counting.

    Parameters
    ----------
    mask : ndarray of bool or integer 0/1, any shape
    voxel_volume_mm3 : float
        Volume of one voxel in mm^3 (see :func:`voxel_volume_mm3`), > 0.

    Returns
    -------
    float
        ``count_nonzero(mask) * voxel_volume_mm3`` in mm^3.

    Examples
    --------
    >>> volume_voxel_mm3(np.ones((2, 3, 4), dtype=bool), voxel_volume_mm3=0.5)
    12.0
    """
    arr = np.asarray(mask)
    if arr.dtype != np.bool_:
        if not np.issubdtype(arr.dtype, np.integer):
            raise InputError(f"mask must be bool or integer 0/1, got dtype {arr.dtype}")
        if arr.size and (arr.min() < 0 or arr.max() > 1):
            raise InputError(
                f"mask must hold only 0 and 1, got values in [{arr.min()}, {arr.max()}]"
            )
    vv = _positive(voxel_volume_mm3, "voxel_volume_mm3", "mm^3")
    return int(np.count_nonzero(arr)) * vv


def voxel_volume_mm3(affine: np.ndarray) -> float:
    """Volume of one voxel: ``|det(affine[:3, :3])|``.

    Parameters
    ----------
    affine : (4, 4) array_like
        Voxel index -> RAS mm; rotations, shears and flips allowed.

    Returns
    -------
    float
        Voxel volume in mm^3.

    Examples
    --------
    >>> round(voxel_volume_mm3(np.diag([-0.9, 0.9, 2.0, 1.0])), 6)
    1.62
    """
    aff = np.asarray(affine)
    if aff.shape != (4, 4) or not np.issubdtype(aff.dtype, np.number):
        raise InputError(f"affine must be a numeric 4x4 array, got shape {aff.shape}")
    aff = aff.astype(np.float64)
    if not np.all(np.isfinite(aff)):
        raise InputError("affine must be finite")
    vol = abs(float(np.linalg.det(aff[:3, :3])))
    if vol == 0.0:
        raise InputError("affine is singular: its voxels have zero volume")
    return vol


def relative_error_percent(estimate: float, truth: float, *, zero_truth: str = "raise") -> float:
    """Relative error of an estimate, Eq. 9: ``|est - truth| / truth * 100``.

    The one implementation of Eq. 9 (the evaluation's
    :func:`tumor3d.evaluation.metrics.relative_error_percent` calls it).

    Parameters
    ----------
    estimate : float
        Estimated value (e.g. pixel count or volume), finite.
    truth : float
        Reference value, finite and > 0 (Eq. 9's denominator N_g).
    zero_truth : {"raise", "nan"}
        A zero reference (a tumour-free case): Eq. 9 is undefined there;
        ``"raise"`` refuses it (InputError), ``"nan"`` returns NaN.

    Returns
    -------
    float
        Percentage, >= 0.

    Examples
    --------
    >>> round(relative_error_percent(3841, 3785), 4)
    1.4795
    >>> relative_error_percent(12, 0, zero_truth="nan")
    nan
    """
    if zero_truth not in ("raise", "nan"):
        raise InputError(f"zero_truth must be 'raise' or 'nan', got {zero_truth!r}")
    est = _finite(estimate, "estimate")
    if zero_truth == "nan" and _finite(truth, "truth") == 0.0:
        return float("nan")
    ref = _positive(truth, "truth", "units")
    return abs(est - ref) / ref * 100.0


def mm3_to_ml(volume_mm3: float) -> float:
    """Convert mm^3 to millilitres (1 ml = 1000 mm^3).

    Examples
    --------
    >>> mm3_to_ml(2500.0)
    2.5
    """
    return _finite(volume_mm3, "volume_mm3") / 1000.0


#: Which acquired slices Eq. 7 sums, by rule name.
EQ7_SLICE_RULES: dict[str, str] = {
    "segmented": (
        "every acquired slice with segmented tumour: the sum runs over the slices "
        "flagged abnormal (one without tumour adds nothing) plus the tumour's "
        "end slices that segmentation found beyond them"
    ),
    "abnormal": "only the slices flagged abnormal (the paper read literally)",
}

Eq7SliceRule = Literal["segmented", "abnormal"]


@dataclass(frozen=True)
class VolumeMeasurement:
    """Every volume estimate of one patient (spec section 8).

    Attributes
    ----------
    volume_eq7_mm3 : float
        Eq. 7 over the slices selected by ``eq7_slice_rule``.
    volume_voxel_mm3 : float
        Voxels of the interpolated 3-D mask times the voxel volume.
    volume_mesh_mm3, volume_mesh_simplified_mm3 : float
        Volume enclosed by the marching-cubes and the simplified mesh (0 when
        there is no mesh).
    n_slices : int
        Acquired slices.
    n_abnormal_slices : int
        Slices flagged abnormal: by the detection, or by the segmentation for a
        method that reads every slice
        (:func:`tumor3d.segmentation.methods.slices_flagged`).
    n_tumor_slices : int
        Acquired slices with at least one segmented tumour pixel.
    n_eq7_slices : int
        Slices Eq. 7 summed.
    eq7_slice_rule : str
        A key of :data:`EQ7_SLICE_RULES`.
    slab_height_mm : float
        Slice thickness + gap (mm).
    pixel_area_mm2 : float
        ``dx * dy`` (mm^2).
    """

    volume_eq7_mm3: float
    volume_voxel_mm3: float
    volume_mesh_mm3: float
    volume_mesh_simplified_mm3: float
    n_slices: int
    n_abnormal_slices: int
    n_tumor_slices: int
    n_eq7_slices: int
    eq7_slice_rule: str
    slab_height_mm: float
    pixel_area_mm2: float

    def to_row(self) -> dict[str, Any]:
        """A flat record: every field, plus each ``*_mm3`` volume again in mL (``*_ml``)."""
        row: dict[str, Any] = {}
        for key, value in asdict(self).items():
            row[key] = value
            if key.startswith("volume_"):
                row[key.replace("_mm3", "_ml")] = mm3_to_ml(value)
        return row


def measure_volumes(
    tumor_pixels: np.ndarray,
    abnormal: np.ndarray,
    fine_mask: np.ndarray,
    fine_affine: np.ndarray,
    *,
    pixel_area_mm2: float,
    slab_height_mm: float,
    mesh: Mesh | None = None,
    mesh_simplified: Mesh | None = None,
    eq7_slices: Eq7SliceRule = "segmented",
) -> VolumeMeasurement:
    r"""Every volume of one patient: Eq. 7, voxel count and mesh volumes.

    Eq. 7 (:func:`volume_eq7_mm3`) sums ``N_i`` over the slices chosen by
    ``eq7_slices``:

    * ``"segmented"`` (default): :math:`\{i : a_i \lor N_i > 0\}`, the slices
      flagged abnormal and those where segmentation found the tumour's tip
      beyond them (a slice holding tumour is abnormal by definition);
    * ``"abnormal"``: :math:`\{i : a_i\}`, the flags alone (the paper's text).

    Parameters
    ----------
    tumor_pixels : (n_slices,) array_like of int
        Tumour pixels ``N_i`` per acquired slice.
    abnormal : (n_slices,) array_like of bool
        The abnormal flags ``a_i`` (the detection's, or the slices with tumour
        of a method that reads every slice:
        :func:`tumor3d.segmentation.methods.slices_flagged`).
    fine_mask : (z, y, x) ndarray of bool
        The interpolated 3-D mask.
    fine_affine : (4, 4) ndarray
        Its affine (``(x, y, z, 1)`` -> RAS mm).
    pixel_area_mm2 : float
        ``dx * dy`` of the acquired slices, > 0.
    slab_height_mm : float
        Thickness + gap, > 0.
    mesh, mesh_simplified : Mesh, optional
        Closed surfaces; an absent or empty mesh has volume 0.
    eq7_slices : {"segmented", "abnormal"}
        The Eq. 7 slice rule (see above and :data:`EQ7_SLICE_RULES`).

    Returns
    -------
    VolumeMeasurement

    Raises
    ------
    InputError
        On an unknown rule or invalid counts, flags or geometry.

    Examples
    --------
    >>> m = measure_volumes([0, 4, 2], [False, True, False], np.zeros((1, 1, 1), bool),
    ...                     np.eye(4), pixel_area_mm2=1.0, slab_height_mm=5.0)
    >>> m.volume_eq7_mm3, m.n_eq7_slices
    (30.0, 2)
    """
    if eq7_slices not in EQ7_SLICE_RULES:
        raise InputError(
            f"eq7_slices must be one of {', '.join(EQ7_SLICE_RULES)}, got {eq7_slices!r}"
        )
    counts = np.asarray(tumor_pixels)
    flags = np.asarray(abnormal)
    if flags.dtype != np.bool_:
        raise InputError(f"abnormal must be a boolean array, got dtype {flags.dtype}")
    if flags.shape != counts.shape:
        raise InputError(
            f"abnormal must have the shape of tumor_pixels {counts.shape}, got {flags.shape}"
        )
    summed = flags | (counts > 0) if eq7_slices == "segmented" else flags
    eq7 = volume_eq7_mm3(
        counts, summed, pixel_area_mm2=pixel_area_mm2, slab_height_mm=slab_height_mm
    )
    voxel = volume_voxel_mm3(fine_mask, voxel_volume_mm3=voxel_volume_mm3(fine_affine))
    mesh_volumes = []
    for m in (mesh, mesh_simplified):
        if m is not None and not isinstance(m, Mesh):
            raise TypeError(
                f"mesh must be a tumor3d.geometry.mesh.Mesh or None, got {type(m).__name__}"
            )
        mesh_volumes.append(0.0 if m is None or m.is_empty else float(mesh_volume_mm3(m)))
    return VolumeMeasurement(
        volume_eq7_mm3=float(eq7),
        volume_voxel_mm3=float(voxel),
        volume_mesh_mm3=mesh_volumes[0],
        volume_mesh_simplified_mm3=mesh_volumes[1],
        n_slices=int(counts.size),
        n_abnormal_slices=int(np.count_nonzero(flags)),
        n_tumor_slices=int(np.count_nonzero(counts)),
        n_eq7_slices=int(np.count_nonzero(summed)),
        eq7_slice_rule=eq7_slices,
        slab_height_mm=float(slab_height_mm),
        pixel_area_mm2=float(pixel_area_mm2),
    )
