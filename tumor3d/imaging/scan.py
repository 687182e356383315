"""The `Scan` data model: one patient's stack of 2-D MR slices, and its source grid.

A `Scan` always holds its image as float32 ``(z, y, x)`` with ``z`` the slice
(acquisition) axis, whatever the voxel order of the file it came from. The
readers permute the voxel axes of the source and reverse some of them (they
never resample), and :class:`SourceGrid` remembers how, so that every output
can be written back in the input's own voxel grid and affine, voxel for voxel.

``Scan.affine`` maps the voxel index ``(x, y, z, 1)`` to RAS millimetres; use
:meth:`Scan.index_to_ras` to map points given in array order ``(z, y, x)``.

The rest of what this module once held lives by concept (issue 31), and is
re-exported here under its old names:

* :mod:`tumor3d.imaging.identity`: :data:`MODALITIES`, :func:`validate_patient_id`;
* :mod:`tumor3d.imaging.affine`: the affine convention and sheared grids,
  :func:`slice_plane_spacing_mm`, :func:`in_plane_shear`, :func:`slab_height_mm`,
  :func:`zyx_index_to_ras`, :func:`reverse_axes`;
* :mod:`tumor3d.imaging.orientation`: the working orientation,
  :func:`canonical_flips`, :func:`canonical_orientation`, :func:`slice_order_note`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tumor3d.constants import IN_PLANE_ORTHOGONALITY_TOL, REL_TOL
from tumor3d.errors import InputError
from tumor3d.imaging.affine import (
    in_plane_shear,
    reverse_axes,
    slab_height_mm,
    slice_plane_spacing_mm,
    zyx_index_to_ras,
)
from tumor3d.imaging.identity import MODALITIES, validate_patient_id
from tumor3d.imaging.orientation import canonical_flips, canonical_orientation, slice_order_note

__all__ = [
    "MODALITIES",
    "Scan",
    "SourceGrid",
    "canonical_flips",
    "canonical_orientation",
    "in_plane_shear",
    "reverse_axes",
    "slab_height_mm",
    "slice_order_note",
    "slice_plane_spacing_mm",
    "validate_patient_id",
    "zyx_index_to_ras",
]


@dataclass(frozen=True, eq=False)
class SourceGrid:
    """How a `Scan`'s ``(z, y, x)`` array maps back to its source voxel grid.

    Parameters
    ----------
    shape : tuple of int
        Voxel shape of the source volume, in the source's own axis order.
    affine : (4, 4) ndarray
        The source's own affine (voxel index in source order -> RAS mm).
    axes : tuple of int
        ``axes[k]`` is the source voxel axis that became Scan axis ``k`` of
        ``(x, y, z)``; ``(0, 1, 2)`` when no permutation was needed.
    flips : tuple of bool
        ``flips[k]``: Scan axis ``k`` of ``(x, y, z)`` runs against source
        axis ``axes[k]`` (index ``i`` of the Scan is ``n - 1 - i`` of the
        source); none when the source already ran as the working orientation.
    xform_codes : tuple of int
        The NIfTI ``(sform_code, qform_code)`` of the source file, which the outputs on
        its grid keep (:func:`tumor3d.storage.nifti.mask_to_source_nifti_bytes`); ``(1,
        1)`` (scanner anatomical) for every other source. ``(0, 0)``: the file states no
        orientation, and its outputs state none either, so that a viewer places them
        where it places the file.
    qform : (4, 4) ndarray or None
        The file's qform (source-order voxel index -> RAS mm) where it states one that
        differs from ``affine`` (the sform, which nibabel and tumor3d read). ITK, so 3D
        Slicer and ITK-SNAP, reads the qform unless the sform code is 1: the outputs
        carry it, mapped onto their own grid, so that those viewers place them where
        they place the file (:meth:`qform_of`).
    """

    shape: tuple[int, int, int]
    affine: np.ndarray
    axes: tuple[int, int, int] = (0, 1, 2)
    flips: tuple[bool, bool, bool] = (False, False, False)
    xform_codes: tuple[int, int] = (1, 1)
    qform: np.ndarray | None = None

    def __post_init__(self) -> None:
        if sorted(self.axes) != [0, 1, 2]:
            raise ValueError(f"axes must be a permutation of (0, 1, 2), got {self.axes}")
        aff = np.array(self.affine, dtype=np.float64)
        if aff.shape != (4, 4):
            raise ValueError(f"affine must be 4x4, got shape {aff.shape}")
        aff.setflags(write=False)
        object.__setattr__(self, "affine", aff)
        object.__setattr__(self, "shape", tuple(int(s) for s in self.shape))
        object.__setattr__(self, "axes", tuple(int(a) for a in self.axes))
        if len(self.flips) != 3:
            raise ValueError(f"flips must hold 3 booleans, got {self.flips}")
        object.__setattr__(self, "flips", tuple(bool(f) for f in self.flips))
        codes = tuple(int(c) for c in self.xform_codes)
        if len(codes) != 2 or not all(0 <= c <= 5 for c in codes):
            raise ValueError(f"xform_codes must be two NIfTI codes 0-5, got {self.xform_codes}")
        object.__setattr__(self, "xform_codes", codes)
        if self.qform is not None:
            q = np.array(self.qform, dtype=np.float64)
            if q.shape != (4, 4):
                raise ValueError(f"qform must be 4x4, got shape {q.shape}")
            q.setflags(write=False)
            object.__setattr__(self, "qform", q)

    def qform_of(self, source_affine: np.ndarray) -> np.ndarray:
        """The qform of a volume written in the source's axis order with ``source_affine``.

        ``source_affine`` itself, unless the file's qform differs from its sform
        (``qform``): then the volume's voxels are taken through the file's voxel
        coordinates into the qform's world, ``qform @ inv(affine) @ source_affine``, so
        that a reader of qforms places the volume on the file as it places the file.

        >>> shifted = SourceGrid((2, 2, 2), np.eye(4), qform=np.array(
        ...     [[1.0, 0, 0, 5], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]))
        >>> shifted.qform_of(np.diag([1.0, 1.0, 0.25, 1.0]))[:3, 3].tolist()
        [5.0, 0.0, 0.0]
        """
        aff = np.asarray(source_affine, dtype=np.float64)
        if self.qform is None:
            return aff
        return self.qform @ np.linalg.inv(self.affine) @ aff

    def _flip_zyx(self, array_zyx: np.ndarray) -> np.ndarray:
        """Reverse the ``(z, y, x)`` axes named by ``flips`` (its own inverse)."""
        out = array_zyx
        for k, flipped in enumerate(self.flips):
            if flipped:
                out = np.flip(out, 2 - k)
        return out

    def from_source(self, array: np.ndarray) -> np.ndarray:
        """Return a source-order array on the Scan's ``(z, y, x)`` grid (C-contiguous).

        The inverse of :meth:`to_source`: a mask given in the input file's voxel order.
        """
        arr = np.asarray(array)
        if arr.shape != self.shape:
            raise ValueError(
                f"array of shape {arr.shape} does not match the source grid {self.shape}"
            )
        return np.ascontiguousarray(self._flip_zyx(arr.transpose(self.axes[::-1])))

    def to_source(self, array_zyx: np.ndarray) -> np.ndarray:
        """Return a Scan-grid ``(z, y, x)`` array in the source's voxel order."""
        xyz = self._flip_zyx(np.asarray(array_zyx)).transpose(2, 1, 0)
        inverse = np.argsort(self.axes)
        out = xyz.transpose(inverse)
        if out.shape != self.shape:
            raise ValueError(
                f"array of shape {np.shape(array_zyx)} (z, y, x) does not match the "
                f"source grid {self.shape}"
            )
        return out

    def to_source_with_affine(
        self, array_zyx: np.ndarray, affine_xyz: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Put an array on another grid in the source's axis order.

        Used for volumes that share the scan's world space but not its grid
        (the finely interpolated mask): the axes are reversed and permuted as
        the source's are, and the affine's columns with them, so world
        positions are kept.

        Parameters
        ----------
        array_zyx : ndarray, shape (z, y, x)
        affine_xyz : (4, 4) ndarray
            Maps ``(x, y, z, 1)`` of ``array_zyx`` to RAS mm.

        Returns
        -------
        array : ndarray
            Voxel array in source axis order.
        affine : (4, 4) ndarray
            Its affine (source-order voxel index -> RAS mm).
        """
        arr, aff = reverse_axes(np.asarray(array_zyx), np.asarray(affine_xyz), self.flips)
        xyz = arr.transpose(2, 1, 0)
        inverse = np.argsort(self.axes)
        new_aff = np.eye(4)
        new_aff[:3, 3] = aff[:3, 3]
        # source axis a holds Scan axis inverse[a]
        for a in range(3):
            new_aff[:3, a] = aff[:3, inverse[a]]
        return xyz.transpose(inverse), new_aff


@dataclass(frozen=True, eq=False)
class Scan:
    """One patient's stack of 2-D slices with its geometry.

    Parameters
    ----------
    image : ndarray, float32, shape (z, y, x)
        Intensities; ``z`` is the slice axis. Made read-only.
    affine : (4, 4) ndarray
        Maps the voxel index ``(x, y, z, 1)`` to RAS millimetres.
    pixel_spacing_mm : tuple of float
        In-plane spacing ``(dy, dx)``: row step and column step in mm (the
        lengths of the affine's y and x columns, checked to 1 %; the two
        columns must be perpendicular).
    slice_step_mm : float
        Centre-to-centre distance of consecutive slice planes, in mm: the
        affine's :func:`slice_plane_spacing_mm` (checked to 1 %), which for a
        sheared grid is less than the slice-axis column's length.
    slice_thickness_mm : float
        Nominal thickness of one slice, in mm.
    slice_gap_mm : float or None
        ``slice_step_mm - slice_thickness_mm`` where known, else ``None``.
    modality : str
        ``"t2"``, ``"flair"`` or ``"t1c"``.
    patient_id : str
        De-identified, folder-safe id (see :func:`validate_patient_id`).
    source : str
        Human-readable description of where the data came from; never holds
        protected health information.
    source_grid : SourceGrid
        How to write Scan-grid arrays back in the source's voxel grid.
    skipped_files : tuple of str
        Names (relative to the input folder) of files the reader skipped as
        unreadable on request (DICOM ``skip_unreadable``); empty otherwise.
        The summary and provenance should list them.
    orientation_stated : bool
        The input states its orientation. False for a folder of 2-D slices (its
        axes are assumed LPS) and a NIfTI header with sform and qform codes 0
        (nibabel's default axes): the affine's directions are then a convention.
    """

    image: np.ndarray
    affine: np.ndarray
    pixel_spacing_mm: tuple[float, float]
    slice_step_mm: float
    slice_thickness_mm: float
    slice_gap_mm: float | None
    modality: str
    patient_id: str
    source: str
    source_grid: SourceGrid = field(repr=False)
    skipped_files: tuple[str, ...] = ()
    orientation_stated: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "skipped_files", tuple(str(f) for f in self.skipped_files))
        img = np.asarray(self.image)
        if img.ndim != 3:
            raise InputError(f"a Scan image must be 3-D (z, y, x), got shape {img.shape}")
        if img.dtype != np.float32:
            img = img.astype(np.float32)
        else:
            img = img.copy() if img.flags.writeable else img
        img.setflags(write=False)
        object.__setattr__(self, "image", img)
        aff = np.array(self.affine, dtype=np.float64)
        if aff.shape != (4, 4):
            raise InputError(f"affine must be 4x4, got shape {aff.shape}")
        aff.setflags(write=False)
        object.__setattr__(self, "affine", aff)
        dy, dx = (float(v) for v in self.pixel_spacing_mm)
        object.__setattr__(self, "pixel_spacing_mm", (dy, dx))
        for name, value in (
            ("pixel spacing dy", dy),
            ("pixel spacing dx", dx),
            ("slice step", self.slice_step_mm),
            ("slice thickness", self.slice_thickness_mm),
        ):
            if not np.isfinite(value) or value <= 0:
                raise InputError(f"{name} must be a positive number of mm, got {value}")
        self._check_geometry(aff, dy, dx)
        validate_patient_id(self.patient_id)
        if self.modality not in MODALITIES:
            raise InputError(
                f"unknown modality {self.modality!r}: expected one of {', '.join(MODALITIES)}"
            )

    def _check_geometry(self, aff: np.ndarray, dy: float, dx: float) -> None:
        """The stated spacings must be those of the affine (no silent inflation of Eq. 7)."""
        shear = in_plane_shear(aff)
        if shear > IN_PLANE_ORTHOGONALITY_TOL:
            raise InputError(
                "the affine's in-plane axes are not perpendicular (1 - sin(angle) = "
                f"{shear:.3g}): the pixel area would not be dx * dy"
            )
        col_x, col_y = np.linalg.norm(aff[:3, 0]), np.linalg.norm(aff[:3, 1])
        plane = slice_plane_spacing_mm(aff)
        for name, stated, actual in (
            ("pixel spacing dx", dx, col_x),
            ("pixel spacing dy", dy, col_y),
            ("slice step", float(self.slice_step_mm), plane),
        ):
            if abs(stated - actual) > REL_TOL * actual:
                raise InputError(
                    f"{name} {stated:.6g} mm disagrees with the affine's {actual:.6g} mm "
                    "(more than 1 %; the slice step is the distance between slice planes)"
                )

    @property
    def voxel_volume_mm3(self) -> float:
        """Volume of one voxel, ``|det(affine[:3, :3])|`` in mm^3 (= dx * dy * step)."""
        return abs(float(np.linalg.det(self.affine[:3, :3])))

    @property
    def shape(self) -> tuple[int, int, int]:
        """Array shape ``(z, y, x)``."""
        return tuple(self.image.shape)  # type: ignore[return-value]

    @property
    def n_slices(self) -> int:
        """Number of acquired slices."""
        return int(self.image.shape[0])

    @property
    def spacing_zyx_mm(self) -> tuple[float, float, float]:
        """Voxel spacing in array order ``(slice step, dy, dx)`` in mm."""
        return (float(self.slice_step_mm), *self.pixel_spacing_mm)

    @property
    def pixel_area_mm2(self) -> float:
        """Area of one pixel, ``dx * dy`` in mm^2 (Eq. 8, [A26]), = ``|c_x x c_y|``."""
        return self.pixel_spacing_mm[0] * self.pixel_spacing_mm[1]

    @property
    def slab_height_mm(self) -> float:
        """Slice thickness + gap, the slab height of Eq. 7 (see :func:`slab_height_mm`)."""
        return slab_height_mm(self.slice_step_mm, self.slice_thickness_mm, self.slice_gap_mm)

    def index_to_ras(self, points_zyx: np.ndarray) -> np.ndarray:
        """Map ``(z, y, x)`` voxel indices to RAS mm (see :func:`zyx_index_to_ras`)."""
        return zyx_index_to_ras(points_zyx, self.affine)
