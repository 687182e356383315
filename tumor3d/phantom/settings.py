"""The arguments of :func:`~tumor3d.phantom.make_phantom_patient`: checks and defaults."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tumor3d.errors import InputError
from tumor3d.imaging.identity import validate_patient_id
from tumor3d.phantom.raster import TISSUE_INTENSITIES
from tumor3d.validation import check_int, check_positive

# Presets: in-plane matrix (rows, columns) and pixel spacing in mm.
_PRESETS: dict[str, tuple[tuple[int, int], float]] = {
    "default": ((256, 256), 0.9375),  # 240 x 240 mm
    "paper": ((480, 640), 0.45),  # 216 mm (rows, A-P) x 288 mm (columns, L-R)
}


@dataclass(frozen=True)
class _Settings:
    """The validated arguments of :func:`~tumor3d.phantom.make_phantom_patient`.

    ``matrix`` is ``(rows, columns)`` = ``(ny, nx)``; ``n_slices`` is None
    when the slices are to cover the whole head (the count then depends on
    the head drawn).
    """

    seed: int
    preset: str
    modality: str
    tumor: bool
    patient_id: str
    matrix: tuple[int, int]
    pixel_spacing_mm: float
    slice_thickness_mm: float
    slice_gap_mm: float
    slice_step_mm: float
    n_slices: int | None
    noise_fraction: float
    bias_field_strength: float
    fine_step_mm: float
    n_sub_xy: int
    n_sub_z: int


def _validated_settings(
    seed: int,
    *,
    preset: str,
    tumor: bool,
    modality: str,
    patient_id: str | None,
    n_slices: int | None,
    matrix_size: tuple[int, int] | None,
    pixel_spacing_mm: float | None,
    slice_thickness_mm: float,
    slice_gap_mm: float,
    noise_fraction: float,
    bias_field_strength: float,
    fine_step_mm: float,
    inplane_subsamples: int,
    slab_subsamples: int,
) -> _Settings:
    """Check the arguments of :func:`~tumor3d.phantom.make_phantom_patient`, resolve defaults.

    Raises
    ------
    InputError
        On the first invalid argument, in the order of the signature (the
        in-plane grid after ``patient_id``).
    """
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise InputError(f"seed must be a non-negative integer, got {seed!r}")
    if preset not in _PRESETS:
        raise InputError(f"preset must be one of {sorted(_PRESETS)}, got {preset!r}")
    if modality not in TISSUE_INTENSITIES:
        raise InputError(f"modality must be one of {sorted(TISSUE_INTENSITIES)}, got {modality!r}")
    if not isinstance(tumor, bool | np.bool_):
        raise InputError(f"tumor must be True or False, got {tumor!r}")
    pid = f"phantom-{int(seed)}" if patient_id is None else validate_patient_id(patient_id)
    matrix, spacing = _in_plane_grid(preset, matrix_size, pixel_spacing_mm)
    thickness = check_positive(slice_thickness_mm, "slice_thickness_mm", unit="mm")
    gap = check_positive(slice_gap_mm, "slice_gap_mm", allow_zero=True, unit="mm")
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
    return _Settings(
        seed=int(seed),
        preset=preset,
        modality=modality,
        tumor=bool(tumor),
        patient_id=pid,
        matrix=matrix,
        pixel_spacing_mm=spacing,
        slice_thickness_mm=thickness,
        slice_gap_mm=gap,
        slice_step_mm=thickness + gap,
        n_slices=n_slices,
        noise_fraction=noise_fraction,
        bias_field_strength=bias_field_strength,
        fine_step_mm=fine_step_mm,
        n_sub_xy=n_sub_xy,
        n_sub_z=n_sub_z,
    )


def _in_plane_grid(
    preset: str,
    matrix_size: tuple[int, int] | None,
    pixel_spacing_mm: float | None,
) -> tuple[tuple[int, int], float]:
    """The in-plane ``(rows, columns)`` matrix and square pixel spacing in mm.

    Either one not given is chosen to keep the preset's field of view; neither
    given gives the preset's.
    """
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
    return matrix, spacing
