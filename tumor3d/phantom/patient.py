"""Patient assembly: place the tumour, render the slices, add bias and Rician noise."""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np

from tumor3d.errors import InputError
from tumor3d.imaging.identity import validate_patient_id
from tumor3d.imaging.scan import Scan, SourceGrid
from tumor3d.phantom.head import _T_CSF_MM, _Head, _random_head
from tumor3d.phantom.raster import (
    _MONOMIALS,
    _TUMOR,
    LABEL_NAMES,
    TISSUE_INTENSITIES,
    _head_fields_many,
    _mask_in_box,
    _render,
)
from tumor3d.phantom.shape import TumorShape, _scaled_shape, random_tumor_shape, tumor_volume_mm3
from tumor3d.validation import check_int, check_positive

# Presets: in-plane matrix (rows, columns) and pixel spacing in mm.
_PRESETS: dict[str, tuple[tuple[int, int], float]] = {
    "default": ((256, 256), 0.9375),  # 240 x 240 mm
    "paper": ((480, 640), 0.45),  # 216 mm (rows, A-P) x 288 mm (columns, L-R)
}


def _place_tumor(
    rng: np.random.Generator,
    head: _Head,
    z_range: tuple[float, float],
) -> tuple[TumorShape, dict[str, Any]]:
    """Draw a tumour inside one hemisphere's brain and inside ``z_range``.

    The whole surface must lie 1 mm inside the grey-matter/CSF boundary,
    at least 3 mm from the mid-sagittal plane, and within ``z_range``. If
    200 random centres fail, the tumour shrinks by 8 % and is tried again.
    """
    target_d = rng.uniform(25.0, 45.0)
    shape0 = random_tumor_shape(rng, equivalent_diameter_mm=target_d)
    side = float(rng.choice([-1.0, 1.0]))
    surf0 = shape0.surface_points(32, 64)
    packed = head.packed()
    thr_csf_inner = packed[9]
    margin = 1.0 * packed[12]  # 1 mm in rho_b units
    brain = head.semi_axes * (1.0 - (head.t_scalp + head.t_skull + _T_CSF_MM) / head.a_ref)
    factor = 1.0
    for _ in range(20):
        surf = surf0 * factor
        lo = surf.min(axis=0)
        hi = surf.max(axis=0)
        zlo = z_range[0] + 1.0 - lo[2]
        zhi = z_range[1] - 1.0 - hi[2]
        if zhi > zlo:
            # centre heights: within the slices and the middle 60 % of the brain if possible
            zc_lo, zc_hi = max(zlo, -0.6 * brain[2]), min(zhi, 0.6 * brain[2])
            if zc_hi <= zc_lo:
                zc_lo, zc_hi = zlo, zhi
            for _ in range(200):
                c = np.array(
                    [
                        side * rng.uniform(0.2, 0.6) * brain[0],
                        rng.uniform(-0.5, 0.5) * brain[1],
                        rng.uniform(zc_lo, zc_hi),
                    ]
                )
                pts = np.ascontiguousarray(surf + c)
                if pts[:, 2].min() < z_range[0] + 1.0 or pts[:, 2].max() > z_range[1] - 1.0:
                    continue
                if np.any(side * pts[:, 0] < 3.0):
                    continue
                fields = _head_fields_many(pts, packed, head.wob_h, head.wob_b)
                if np.all(fields[:, 1] < thr_csf_inner - margin):
                    shape = _scaled_shape(shape0, factor, c)
                    return shape, {
                        "target_equivalent_diameter_mm": float(target_d),
                        "scale_factor": factor,
                        "hemisphere": "left" if side < 0 else "right",
                    }
        factor *= 0.92
        if target_d * factor < 10.0:
            break
    raise InputError(
        f"n_slices: the slices cover z in [{z_range[0]:.1f}, {z_range[1]:.1f}] mm, too "
        "little of the brain to hold a tumour of >= 10 mm; use more slices or tumor=False"
    )


# ---------------------------------------------------------------------------
# Patient
# ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class PhantomPatient:
    """A synthetic patient and its ground truth.

    Parameters
    ----------
    scan : Scan
        The thick-slice acquisition: float32 ``(z, y, x)`` image.
    slice_masks : bool ndarray, shape (z, y, x)
        True tumour cross-section at each acquired slice's centre plane
        (a pixel is inside iff its centre is).
    fine_mask : bool ndarray, shape (Z, y, x)
        True tumour on a fine grid: same in-plane grid, planes every
        ``fine_step_mm`` from the first to the last slice centre (so every
        ``step / fine_step``-th plane is an acquired slice's centre plane).
    fine_affine : (4, 4) ndarray
        ``(x, y, z, 1)`` index of ``fine_mask`` -> RAS mm.
    tissue_labels : uint8 ndarray, shape (z, y, x)
        Label at each pixel centre of each slice centre plane
        (see :data:`LABEL_NAMES`).
    true_volume_mm3 : float
        Exact tumour volume (0.0 without tumour).
    params : dict
        JSON-able description of everything that was drawn.
    tumor_shape : TumorShape or None
        The tumour, for inside-tests at arbitrary points.

    All arrays are read-only.
    """

    scan: Scan
    slice_masks: np.ndarray
    fine_mask: np.ndarray
    fine_affine: np.ndarray
    tissue_labels: np.ndarray
    true_volume_mm3: float
    params: dict
    tumor_shape: TumorShape | None = None

    def __post_init__(self) -> None:
        for name in ("slice_masks", "fine_mask", "fine_affine", "tissue_labels"):
            arr = np.asarray(getattr(self, name))
            if arr.flags.writeable:
                arr = arr.copy()
                arr.setflags(write=False)
            object.__setattr__(self, name, arr)


def make_phantom_patient(
    seed: int,
    *,
    preset: Literal["default", "paper"] = "default",
    tumor: bool = True,
    modality: Literal["t2", "flair"] = "t2",
    patient_id: str | None = None,
    n_slices: int | None = None,
    matrix_size: tuple[int, int] | None = None,
    pixel_spacing_mm: float | None = None,
    slice_thickness_mm: float = 2.0,
    slice_gap_mm: float = 3.0,
    noise_fraction: float = 0.03,
    bias_field_strength: float = 0.15,
    fine_step_mm: float = 0.5,
    inplane_subsamples: int = 3,
    slab_subsamples: int = 4,
) -> PhantomPatient:
    """Make a synthetic thick-slice MR patient with known ground truth.

    Parameters
    ----------
    seed : int
        Non-negative seed; everything is deterministic in it. The head, the
        tumour, the bias field and the noise come from independent streams
        (``numpy.random.SeedSequence(seed).spawn(4)``), so ``tumor=False``
        gives the same head as ``tumor=True``.
    preset : {"default", "paper"}
        ``"default"``: 256 x 256 pixels of 0.9375 mm (240 mm FOV).
        ``"paper"``: 480 rows x 640 columns of 0.45 mm (216 x 288 mm; the
        paper's 640 x 480 images, with pixels small enough for the head's
        ~190 mm antero-posterior length to fit the 480 rows).
    tumor : bool
        Plant a tumour (else all truth masks are empty and the volume 0).
    modality : {"t2", "flair"}
        Contrast (see :data:`TISSUE_INTENSITIES`).
    patient_id : str, optional
        Defaults to ``"phantom-<seed>"``.
    n_slices : int, optional
        Number of slices, centred on the head; by default enough to cover
        the whole head (about 28-31 at a 5 mm step). The tumour is placed
        (and if need be shrunk) to lie between the first and last slice.
    matrix_size : (int, int), optional
        ``(rows, columns)`` = ``(ny, nx)``, the image's in-plane array shape.
        Without ``pixel_spacing_mm`` the spacing is chosen to keep the
        preset's field of view.
    pixel_spacing_mm : float, optional
        Square pixel size; without ``matrix_size`` the matrix is chosen to
        keep the preset's field of view.
    slice_thickness_mm, slice_gap_mm : float
        Slice thickness (> 0) and gap (>= 0); the slice step is their sum.
    noise_fraction : float
        Rician noise ``sigma`` as a fraction of the maximum noise-free
        intensity, in [0, 1).
    bias_field_strength : float
        Maximum relative deviation of the multiplicative bias field over the
        head, in [0, 0.9].
    fine_step_mm : float
        Plane spacing of :attr:`PhantomPatient.fine_mask`.
    inplane_subsamples, slab_subsamples : int
        Partial-volume sub-samples per pixel side and through the thickness.

    Returns
    -------
    PhantomPatient

    Raises
    ------
    InputError
        On any invalid argument, if the field of view cannot hold the head,
        or if ``n_slices`` covers too little of the brain to hold a tumour.

    Notes
    -----
    Affine: columns run to patient left, rows to posterior, slices to
    superior: ``[[-dx, 0, 0, ox], [0, -dy, 0, oy], [0, 0, step, oz]]`` with
    the origin chosen so that the grid centre is RAS ``(0, 0, 0)``, the head
    centre.
    """
    # ---- validation -------------------------------------------------------
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise InputError(f"seed must be a non-negative integer, got {seed!r}")
    seed = int(seed)
    if preset not in _PRESETS:
        raise InputError(f"preset must be one of {sorted(_PRESETS)}, got {preset!r}")
    if modality not in TISSUE_INTENSITIES:
        raise InputError(f"modality must be one of {sorted(TISSUE_INTENSITIES)}, got {modality!r}")
    if not isinstance(tumor, bool | np.bool_):
        raise InputError(f"tumor must be True or False, got {tumor!r}")
    pid = f"phantom-{seed}" if patient_id is None else validate_patient_id(patient_id)
    preset_matrix, preset_spacing = _PRESETS[preset]
    fov = np.array(preset_matrix) * preset_spacing  # (rows, cols) in mm
    if matrix_size is not None:
        if (
            not isinstance(matrix_size, tuple | list)
            or len(matrix_size) != 2
            or any(
                isinstance(m, bool) or not isinstance(m, int | np.integer) or m < 8
                for m in matrix_size
            )
        ):
            raise InputError(
                f"matrix_size must be two integers (rows, columns) >= 8, got {matrix_size!r}"
            )
        matrix = (int(matrix_size[0]), int(matrix_size[1]))
    if pixel_spacing_mm is not None:
        spacing = check_positive(pixel_spacing_mm, "pixel_spacing_mm", unit="mm")
    if matrix_size is None and pixel_spacing_mm is None:
        matrix, spacing = preset_matrix, preset_spacing
    elif matrix_size is None:
        matrix = tuple(int(m) for m in np.ceil(fov / spacing - 1e-9))
    elif pixel_spacing_mm is None:
        spacing = float(np.max(fov / np.array(matrix)))
    thickness = check_positive(slice_thickness_mm, "slice_thickness_mm", unit="mm")
    gap = check_positive(slice_gap_mm, "slice_gap_mm", allow_zero=True, unit="mm")
    step = thickness + gap
    noise_fraction = check_positive(noise_fraction, "noise_fraction", allow_zero=True)
    if noise_fraction >= 1.0:
        raise InputError(f"noise_fraction must be < 1, got {noise_fraction!r}")
    bias_field_strength = check_positive(
        bias_field_strength, "bias_field_strength", allow_zero=True
    )
    if bias_field_strength > 0.9:
        raise InputError(f"bias_field_strength must be <= 0.9, got {bias_field_strength!r}")
    fine_step_mm = check_positive(fine_step_mm, "fine_step_mm", unit="mm")
    n_sub_xy = check_int(inplane_subsamples, "inplane_subsamples", minimum=1)
    n_sub_z = check_int(slab_subsamples, "slab_subsamples", minimum=1)
    if n_slices is not None:
        n_slices = check_int(n_slices, "n_slices", minimum=1)

    # ---- geometry -----------------------------------------------------------
    ss = np.random.SeedSequence(seed)
    rng_head, rng_tumor, rng_bias, rng_noise = (np.random.default_rng(s) for s in ss.spawn(4))
    head = _random_head(rng_head)
    ny, nx = matrix
    ext = head.extent_mm
    if nx * spacing < 2.0 * ext[0] + 4.0 or ny * spacing < 2.0 * ext[1] + 4.0:
        raise InputError(
            f"matrix_size {matrix} x pixel_spacing_mm {spacing:g} gives a "
            f"{ny * spacing:.0f} x {nx * spacing:.0f} mm field of view (rows x columns), too "
            f"small for this head ({2 * ext[1] + 4:.0f} x {2 * ext[0] + 4:.0f} mm needed)"
        )
    if n_slices is None:
        n_slices = int(np.ceil(2.0 * ext[2] / step)) + 1
    nz = n_slices
    affine = np.array(
        [
            [-spacing, 0.0, 0.0, spacing * (nx - 1) / 2.0],
            [0.0, -spacing, 0.0, spacing * (ny - 1) / 2.0],
            [0.0, 0.0, step, -step * (nz - 1) / 2.0],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    z_first, z_last = affine[2, 3], affine[2, 3] + step * (nz - 1)

    shape: TumorShape | None = None
    tumor_info: dict[str, Any] = {}
    if tumor:
        shape, tumor_info = _place_tumor(rng_tumor, head, (z_first, z_last))
        tum, dirs, amps, kappas = shape._packed()
        surf = shape.surface_points(64, 128)
        tum_bbox = np.concatenate([surf.min(axis=0) - 2.0, surf.max(axis=0) + 2.0])
    else:
        tum = np.zeros(20)
        dirs, amps, kappas = np.zeros((0, 3)), np.zeros(0), np.zeros(0)
        tum_bbox = np.array([1.0, 1.0, 1.0, -1.0, -1.0, -1.0])  # empty box

    # ---- image formation ----------------------------------------------------
    values = np.array(TISSUE_INTENSITIES[modality])
    sub_xy = (np.arange(n_sub_xy) + 0.5) / n_sub_xy - 0.5
    sub_z = ((np.arange(n_sub_z) + 0.5) / n_sub_z - 0.5) * thickness / step
    clean, labels = _render(
        affine,
        nz,
        ny,
        nx,
        sub_xy,
        sub_z,
        head.packed(),
        head.wob_h,
        head.wob_b,
        head.ventricles,
        tum,
        dirs,
        amps,
        kappas,
        tum_bbox,
        values,
        True,
    )
    bias, bias_coef = _bias_field(rng_bias, head, affine, (nz, ny, nx), bias_field_strength)
    clean *= bias
    noise_free_max = float(clean.max())
    sigma = noise_fraction * noise_free_max
    clean = clean.astype(np.float32)
    n1 = rng_noise.standard_normal(clean.shape, dtype=np.float32)
    n2 = rng_noise.standard_normal(clean.shape, dtype=np.float32)
    n1 *= np.float32(sigma)
    n1 += clean
    n2 *= np.float32(sigma)
    image = np.hypot(n1, n2)

    # ---- truth --------------------------------------------------------------
    slice_masks = labels == _TUMOR
    n_fine = int(np.floor((nz - 1) * step / fine_step_mm + 1e-9)) + 1
    fine_affine = affine.copy()
    fine_affine[2, 2] = fine_step_mm
    fine_mask = np.zeros((n_fine, ny, nx), dtype=bool)
    volume = 0.0
    if shape is not None:
        volume = tumor_volume_mm3(shape)
        lo, hi = _index_box(fine_affine, tum_bbox, fine_mask.shape)
        _mask_in_box(fine_affine, lo, hi, tum, dirs, amps, kappas, fine_mask)

    for arr in (image, slice_masks, fine_mask, fine_affine, labels):
        arr.setflags(write=False)  # owned here: read-only without a copy
    scan = Scan(
        image=image,
        affine=affine,
        pixel_spacing_mm=(spacing, spacing),
        slice_step_mm=step,
        slice_thickness_mm=thickness,
        slice_gap_mm=gap,
        modality=modality,
        patient_id=pid,
        source=f"synthetic phantom seed={seed} preset={preset} tumor={bool(tumor)}",
        source_grid=SourceGrid(shape=(nx, ny, nz), affine=affine, axes=(0, 1, 2)),
    )
    params: dict[str, Any] = {
        "seed": seed,
        "preset": preset,
        "modality": modality,
        "tumor": bool(tumor),
        "matrix_size_rows_cols": [ny, nx],
        "pixel_spacing_mm": spacing,
        "n_slices": nz,
        "slice_thickness_mm": thickness,
        "slice_gap_mm": gap,
        "slice_step_mm": step,
        "fine_step_mm": fine_step_mm,
        "inplane_subsamples": n_sub_xy,
        "slab_subsamples": n_sub_z,
        "head": head.to_dict(),
        "tissue_intensities": dict(
            zip(LABEL_NAMES.values(), (float(v) for v in values), strict=True)
        ),
        "bias_field_strength": bias_field_strength,
        "bias_field_coefficients": bias_coef,
        "noise_fraction": noise_fraction,
        "noise_free_max": noise_free_max,
        "noise_sigma": sigma,
        "true_volume_mm3": volume,
    }
    if shape is not None:
        params["tumor_shape"] = {
            **shape.to_dict(),
            **tumor_info,
            "equivalent_diameter_mm": float((6.0 * volume / np.pi) ** (1.0 / 3.0)),
            "drift_note": "cross-section centroids drift by the shear s(z) = "
            "sum_k shear_coefficients[:, k] z^(k+1), z relative to center_mm",
        }
    return PhantomPatient(
        scan=scan,
        slice_masks=slice_masks,
        fine_mask=fine_mask,
        fine_affine=fine_affine,
        tissue_labels=labels,
        true_volume_mm3=volume,
        params=params,
        tumor_shape=shape,
    )


def _index_box(affine: np.ndarray, bbox_mm: np.ndarray, shape: tuple[int, int, int]):
    """Index range ``[lo, hi)`` in ``(z, y, x)`` order covering a RAS box ``[min3, max3]``."""
    corners = np.array(list(itertools.product(*zip(bbox_mm[:3], bbox_mm[3:], strict=True))))
    inv = np.linalg.inv(affine)
    idx = corners @ inv[:3, :3].T + inv[:3, 3]  # (x, y, z) indices
    lo_xyz = np.floor(idx.min(axis=0)).astype(np.int64)
    hi_xyz = np.ceil(idx.max(axis=0)).astype(np.int64) + 1
    lo = np.clip(lo_xyz[::-1], 0, shape)
    hi = np.clip(hi_xyz[::-1], 0, shape)
    return lo, hi


def _bias_field(
    rng: np.random.Generator,
    head: _Head,
    affine: np.ndarray,
    shape: tuple[int, int, int],
    strength: float,
) -> tuple[np.ndarray, list[float]]:
    """Smooth multiplicative field ``1 + strength * g(q)``, ``q = p / 100 mm``.

    ``g`` is a random polynomial of degree 1-2 scaled so that ``max |g| = 1``
    over a fixed 21^3 lattice filling the head's bounding ellipsoid (so the
    field does not depend on the image grid).
    """
    mono = _MONOMIALS[_MONOMIALS.sum(axis=1) <= 2]
    coef = rng.normal(size=len(mono))
    g = np.linspace(-1.0, 1.0, 21)
    lat = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    lat = lat[np.linalg.norm(lat, axis=1) <= 1.0] * head.extent_mm

    def poly(p: np.ndarray) -> np.ndarray:
        q = p / 100.0
        return np.prod(q[..., None, :] ** mono, axis=-1) @ coef

    coef = coef / np.abs(poly(lat)).max()
    nz, ny, nx = shape
    # the affine is diagonal: g = sum_e z^e G_e(y, x), three 2-D terms per slice
    x = (affine[0, 0] * np.arange(nx) + affine[0, 3]) / 100.0
    y = (affine[1, 1] * np.arange(ny) + affine[1, 3]) / 100.0
    z = (affine[2, 2] * np.arange(nz) + affine[2, 3]) / 100.0
    planes = np.zeros((3, ny, nx))
    for c, (ex, ey, ez) in zip(coef, mono, strict=True):
        planes[ez] += c * np.outer(y**ey, x**ex)
    field_ = np.empty(shape, dtype=np.float64)
    for k in range(nz):
        field_[k] = 1.0 + strength * (planes[0] + z[k] * planes[1] + z[k] ** 2 * planes[2])
    return field_, [float(c) for c in coef]
