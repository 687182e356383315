"""Patient assembly: place the tumour, render the slices, add bias and Rician noise."""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Any, Literal, NamedTuple

import numpy as np

from tumor3d.errors import InputError
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
from tumor3d.phantom.settings import _Settings, _validated_settings
from tumor3d.phantom.shape import TumorShape, _scaled_shape, random_tumor_shape, tumor_volume_mm3


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
    settings = _validated_settings(
        seed,
        preset=preset,
        tumor=tumor,
        modality=modality,
        patient_id=patient_id,
        n_slices=n_slices,
        matrix_size=matrix_size,
        pixel_spacing_mm=pixel_spacing_mm,
        slice_thickness_mm=slice_thickness_mm,
        slice_gap_mm=slice_gap_mm,
        noise_fraction=noise_fraction,
        bias_field_strength=bias_field_strength,
        fine_step_mm=fine_step_mm,
        inplane_subsamples=inplane_subsamples,
        slab_subsamples=slab_subsamples,
    )
    streams = np.random.SeedSequence(settings.seed).spawn(4)
    rng_head, rng_tumor, rng_bias, rng_noise = (np.random.default_rng(s) for s in streams)
    head = _random_head(rng_head)
    affine, grid_shape = _slice_grid(head, settings)
    shape, tumor_info = _plant_tumor(rng_tumor, head, affine, grid_shape[0], settings)
    tumor_arrays = _tumor_arrays(shape)
    image, labels, formation = _form_image(
        rng_bias, rng_noise, head, tumor_arrays, affine, grid_shape, settings
    )
    truth = _truth(labels, affine, grid_shape, shape, tumor_arrays, settings)
    return PhantomPatient(
        scan=_make_scan(image, affine, grid_shape, settings),
        slice_masks=truth.slice_masks,
        fine_mask=truth.fine_mask,
        fine_affine=truth.fine_affine,
        tissue_labels=labels,
        true_volume_mm3=truth.volume_mm3,
        params=_params_record(
            settings, grid_shape, head, formation, truth.volume_mm3, shape, tumor_info
        ),
        tumor_shape=shape,
    )


# ---------------------------------------------------------------------------
# The steps of make_phantom_patient
# ---------------------------------------------------------------------------


class _TumorArrays(NamedTuple):
    """The tumour as the numba kernels take it (see ``TumorShape._packed``).

    ``bbox_mm`` is ``[min3, max3]`` in RAS mm, 2 mm around the surface; an
    empty box (min > max) without tumour.
    """

    packed: np.ndarray
    dirs: np.ndarray
    amps: np.ndarray
    kappas: np.ndarray
    bbox_mm: np.ndarray


class _Truth(NamedTuple):
    """The ground truth: see the fields of :class:`PhantomPatient`."""

    slice_masks: np.ndarray
    fine_mask: np.ndarray
    fine_affine: np.ndarray
    volume_mm3: float


def _slice_grid(head: _Head, settings: _Settings) -> tuple[np.ndarray, tuple[int, int, int]]:
    """The acquisition's affine and ``(nz, ny, nx)`` shape, centred on the head.

    Without ``settings.n_slices`` the slices cover the whole head.

    Raises
    ------
    InputError
        If the field of view cannot hold the head (with 2 mm to spare each side).
    """
    ny, nx = settings.matrix
    spacing, step = settings.pixel_spacing_mm, settings.slice_step_mm
    ext = head.extent_mm
    if nx * spacing < 2.0 * ext[0] + 4.0 or ny * spacing < 2.0 * ext[1] + 4.0:
        raise InputError(
            f"matrix_size {settings.matrix} x pixel_spacing_mm {spacing:g} gives a "
            f"{ny * spacing:.0f} x {nx * spacing:.0f} mm field of view (rows x columns), too "
            f"small for this head ({2 * ext[1] + 4:.0f} x {2 * ext[0] + 4:.0f} mm needed)"
        )
    nz = settings.n_slices
    if nz is None:
        nz = int(np.ceil(2.0 * ext[2] / step)) + 1
    affine = np.array(
        [
            [-spacing, 0.0, 0.0, spacing * (nx - 1) / 2.0],
            [0.0, -spacing, 0.0, spacing * (ny - 1) / 2.0],
            [0.0, 0.0, step, -step * (nz - 1) / 2.0],
            [0.0, 0.0, 0.0, 1.0],
        ]
    )
    return affine, (nz, ny, nx)


def _plant_tumor(
    rng: np.random.Generator,
    head: _Head,
    affine: np.ndarray,
    n_slices: int,
    settings: _Settings,
) -> tuple[TumorShape | None, dict[str, Any]]:
    """The tumour between the first and last slice centres and its placement record.

    ``(None, {})`` without tumour (``rng`` is then not drawn from).
    """
    if not settings.tumor:
        return None, {}
    z_first_mm = affine[2, 3]
    z_last_mm = affine[2, 3] + settings.slice_step_mm * (n_slices - 1)
    return _place_tumor(rng, head, (z_first_mm, z_last_mm))


def _tumor_arrays(shape: TumorShape | None) -> _TumorArrays:
    """Pack ``shape`` for the kernels; zero-size arrays and an empty box for None."""
    if shape is None:
        return _TumorArrays(
            packed=np.zeros(20),
            dirs=np.zeros((0, 3)),
            amps=np.zeros(0),
            kappas=np.zeros(0),
            bbox_mm=np.array([1.0, 1.0, 1.0, -1.0, -1.0, -1.0]),  # empty box
        )
    packed, dirs, amps, kappas = shape._packed()
    surf = shape.surface_points(64, 128)
    bbox_mm = np.concatenate([surf.min(axis=0) - 2.0, surf.max(axis=0) + 2.0])
    return _TumorArrays(packed, dirs, amps, kappas, bbox_mm)


def _form_image(
    rng_bias: np.random.Generator,
    rng_noise: np.random.Generator,
    head: _Head,
    tumor_arrays: _TumorArrays,
    affine: np.ndarray,
    grid_shape: tuple[int, int, int],
    settings: _Settings,
) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """Render the slices, apply the bias field and add Rician noise.

    Returns
    -------
    image : float32 ndarray, shape (nz, ny, nx)
        Read-only.
    labels : uint8 ndarray, shape (nz, ny, nx)
        Tissue label at each pixel centre of each slice centre plane; read-only.
    record : dict
        The image formation's entries of :attr:`PhantomPatient.params`, in order.
    """
    values = np.array(TISSUE_INTENSITIES[settings.modality])
    clean, labels = _render_slices(head, tumor_arrays, affine, grid_shape, values, settings)
    bias, bias_coef = _bias_field(rng_bias, head, affine, grid_shape, settings.bias_field_strength)
    clean *= bias
    noise_free_max = float(clean.max())
    sigma = settings.noise_fraction * noise_free_max
    image = _add_rician_noise(rng_noise, clean, sigma)
    for arr in (image, labels):
        arr.setflags(write=False)  # owned here: read-only without a copy
    record = {
        "tissue_intensities": dict(
            zip(LABEL_NAMES.values(), (float(v) for v in values), strict=True)
        ),
        "bias_field_strength": settings.bias_field_strength,
        "bias_field_coefficients": bias_coef,
        "noise_fraction": settings.noise_fraction,
        "noise_free_max": noise_free_max,
        "noise_sigma": sigma,
    }
    return image, labels, record


def _render_slices(
    head: _Head,
    tumor_arrays: _TumorArrays,
    affine: np.ndarray,
    grid_shape: tuple[int, int, int],
    values: np.ndarray,
    settings: _Settings,
) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free partial-volume intensities (float64) and labels of every slice.

    Each pixel averages ``n_sub_xy**2`` in-plane sub-samples times ``n_sub_z``
    samples through the slice thickness.
    """
    nz, ny, nx = grid_shape
    n_xy, n_z = settings.n_sub_xy, settings.n_sub_z
    thickness, step = settings.slice_thickness_mm, settings.slice_step_mm
    sub_xy = (np.arange(n_xy) + 0.5) / n_xy - 0.5
    sub_z = ((np.arange(n_z) + 0.5) / n_z - 0.5) * thickness / step
    return _render(
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
        tumor_arrays.packed,
        tumor_arrays.dirs,
        tumor_arrays.amps,
        tumor_arrays.kappas,
        tumor_arrays.bbox_mm,
        values,
        True,
    )


def _add_rician_noise(rng: np.random.Generator, clean: np.ndarray, sigma: float) -> np.ndarray:
    """``sqrt((I + sigma n1)^2 + (sigma n2)^2)`` in float32, ``n1, n2 ~ N(0, 1)``."""
    clean = clean.astype(np.float32)
    n1 = rng.standard_normal(clean.shape, dtype=np.float32)
    n2 = rng.standard_normal(clean.shape, dtype=np.float32)
    n1 *= np.float32(sigma)
    n1 += clean
    n2 *= np.float32(sigma)
    return np.hypot(n1, n2)


def _truth(
    labels: np.ndarray,
    affine: np.ndarray,
    grid_shape: tuple[int, int, int],
    shape: TumorShape | None,
    tumor_arrays: _TumorArrays,
    settings: _Settings,
) -> _Truth:
    """The slice masks, the fine-grid mask and its affine, and the exact volume.

    The fine planes run every ``settings.fine_step_mm`` from the first slice
    centre; all arrays are read-only.
    """
    nz, ny, nx = grid_shape
    slice_masks = labels == _TUMOR
    n_fine = int(np.floor((nz - 1) * settings.slice_step_mm / settings.fine_step_mm + 1e-9)) + 1
    fine_affine = affine.copy()
    fine_affine[2, 2] = settings.fine_step_mm
    fine_mask = np.zeros((n_fine, ny, nx), dtype=bool)
    volume_mm3 = 0.0
    if shape is not None:
        volume_mm3 = tumor_volume_mm3(shape)
        lo, hi = _index_box(fine_affine, tumor_arrays.bbox_mm, fine_mask.shape)
        _mask_in_box(
            fine_affine,
            lo,
            hi,
            tumor_arrays.packed,
            tumor_arrays.dirs,
            tumor_arrays.amps,
            tumor_arrays.kappas,
            fine_mask,
        )
    for arr in (slice_masks, fine_mask, fine_affine):
        arr.setflags(write=False)  # owned here: read-only without a copy
    return _Truth(slice_masks, fine_mask, fine_affine, volume_mm3)


def _make_scan(
    image: np.ndarray,
    affine: np.ndarray,
    grid_shape: tuple[int, int, int],
    settings: _Settings,
) -> Scan:
    """Wrap the image as the thick-slice :class:`Scan` with its provenance."""
    nz, ny, nx = grid_shape
    spacing = settings.pixel_spacing_mm
    return Scan(
        image=image,
        affine=affine,
        pixel_spacing_mm=(spacing, spacing),
        slice_step_mm=settings.slice_step_mm,
        slice_thickness_mm=settings.slice_thickness_mm,
        slice_gap_mm=settings.slice_gap_mm,
        modality=settings.modality,
        patient_id=settings.patient_id,
        source=(
            f"synthetic phantom seed={settings.seed} preset={settings.preset} "
            f"tumor={settings.tumor}"
        ),
        source_grid=SourceGrid(shape=(nx, ny, nz), affine=affine, axes=(0, 1, 2)),
    )


def _params_record(
    settings: _Settings,
    grid_shape: tuple[int, int, int],
    head: _Head,
    formation: dict[str, Any],
    volume_mm3: float,
    shape: TumorShape | None,
    tumor_info: dict[str, Any],
) -> dict[str, Any]:
    """The JSON-able :attr:`PhantomPatient.params`: everything that was drawn or chosen."""
    nz, ny, nx = grid_shape
    params: dict[str, Any] = {
        "seed": settings.seed,
        "preset": settings.preset,
        "modality": settings.modality,
        "tumor": settings.tumor,
        "matrix_size_rows_cols": [ny, nx],
        "pixel_spacing_mm": settings.pixel_spacing_mm,
        "n_slices": nz,
        "slice_thickness_mm": settings.slice_thickness_mm,
        "slice_gap_mm": settings.slice_gap_mm,
        "slice_step_mm": settings.slice_step_mm,
        "fine_step_mm": settings.fine_step_mm,
        "inplane_subsamples": settings.n_sub_xy,
        "slab_subsamples": settings.n_sub_z,
        "head": head.to_dict(),
        **formation,
        "true_volume_mm3": volume_mm3,
    }
    if shape is not None:
        params["tumor_shape"] = {
            **shape.to_dict(),
            **tumor_info,
            "equivalent_diameter_mm": float((6.0 * volume_mm3 / np.pi) ** (1.0 / 3.0)),
            "drift_note": "cross-section centroids drift by the shear s(z) = "
            "sum_k shear_coefficients[:, k] z^(k+1), z relative to center_mm",
        }
    return params


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
