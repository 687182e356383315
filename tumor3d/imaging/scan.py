"""The `Scan` data model: one patient's stack of 2-D MR slices.

A `Scan` always holds its image as float32 ``(z, y, x)`` with ``z`` the slice
(acquisition) axis, whatever the voxel order of the file it came from. The
readers permute the voxel axes of the source and reverse some of them (they
never resample), and :class:`SourceGrid` remembers how, so that every output
can be written back in the input's own voxel grid and affine, voxel for voxel.

Working orientation
-------------------
The readers reverse the Scan axes that run against the working orientation
(:func:`canonical_flips`, :func:`canonical_orientation`): ``x`` towards the
patient's left, rows (``y``) towards posterior on an axial slice and towards
inferior on a coronal or sagittal one, slices (``z``) towards superior on an
axial stack (left on a sagittal one, posterior on a coronal one). This is how
DICOM and the BraTS volumes store an axial head (LPS), and so how the learned
method's training scans ran: its position features and its U-Net read an
array, and a patient stored the other way (a LAS NIfTI, slices from the top
down) would otherwise be another input to them (one BraTS FLAIR stored LAS
lost 16 % of its learned volume).

Affine convention
-----------------
``Scan.affine`` is 4x4 and maps the voxel index ``(x, y, z, 1)`` to RAS
millimetres, i.e. the affine nibabel would report for the array
``image.transpose(2, 1, 0)``. Use :meth:`Scan.index_to_ras` to map points
given in array order ``(z, y, x)``.

Sheared grids
-------------
The slice-axis column of the affine need not be perpendicular to the slice
plane (a NIfTI converted from a gantry-tilted series has such a shear). The
slice *step* is then the distance between slice planes, not the length of
that column: with ``c_x, c_y, c_z`` the affine's first three columns,

    step = |det [c_x c_y c_z]| / |c_x x c_y|

(:func:`slice_plane_spacing_mm`), so that one pixel area times the step is
the voxel volume ``|det|`` and the slab volumes of Eq. 7 add up to the
voxel-counted volume. The two in-plane columns must be perpendicular (to
:data:`tumor3d.constants.IN_PLANE_ORTHOGONALITY_TOL`), so that the pixel area
is ``dx * dy``.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace

import numpy as np

from tumor3d.constants import IN_PLANE_ORTHOGONALITY_TOL, REL_TOL, SHEAR_TOL, SINGULAR_DET_TOL
from tumor3d.errors import InputError

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

#: The MR sequences the pipeline knows (they decide which cluster is tumour).
MODALITIES = ("t2", "flair", "t1c")

_SAFE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,127}$")


def validate_patient_id(patient_id: str) -> str:
    """Check that a patient id is a safe, single folder name.

    Parameters
    ----------
    patient_id : str
        Candidate id: 1-128 characters from ``[A-Za-z0-9._-]``, starting
        with a letter or digit (so never ``.``, ``..`` or a hidden name),
        with no path separator.

    Returns
    -------
    str
        The id, unchanged.

    Raises
    ------
    InputError
        If the id is empty, too long, or contains any other character.

    Examples
    --------
    >>> validate_patient_id("pat-0003")
    'pat-0003'
    """
    if not isinstance(patient_id, str) or not _SAFE_ID.match(patient_id):
        raise InputError(
            f"unsafe patient id {patient_id!r}: use 1-128 characters from "
            "letters, digits, '.', '_' and '-', starting with a letter or digit "
            "(no path separators, no '..')"
        )
    return patient_id


def slab_height_mm(
    slice_step_mm: float, slice_thickness_mm: float, slice_gap_mm: float | None
) -> float:
    """Slab height of Eq. 7: thickness + gap, or the step where the gap is unknown.

    Parameters
    ----------
    slice_step_mm : float
        Distance between consecutive slice *planes* in mm (for a sheared
        grid: :func:`slice_plane_spacing_mm`, never the slice-axis column's
        length). ``Scan.slice_step_mm`` always is.
    slice_thickness_mm : float
        Nominal slice thickness in mm.
    slice_gap_mm : float or None
        Gap between slices in mm, ``None`` if unknown.

    Returns
    -------
    float
        ``slice_thickness_mm + slice_gap_mm``, or ``slice_step_mm`` when the
        gap is unknown, in mm.
    """
    if slice_gap_mm is None:
        return float(slice_step_mm)
    return float(slice_thickness_mm + slice_gap_mm)


def slice_plane_spacing_mm(affine: np.ndarray, slice_axis: int = 2) -> float:
    """Distance between consecutive slice planes of a voxel grid, in mm.

    The slice-axis column ``c_s`` projected on the unit normal of the plane
    spanned by the two other columns ``c_a, c_b``:

        spacing = |c_s . (c_a x c_b)| / |c_a x c_b| = |det A| / |c_a x c_b|

    It equals the column length ``|c_s|`` only when the grid is not sheared;
    when the two differ by at most :data:`tumor3d.constants.SHEAR_TOL`
    (relative), the column length is returned, free of round-off.

    Parameters
    ----------
    affine : (4, 4) array_like
        Voxel index -> world mm.
    slice_axis : {0, 1, 2}
        The voxel axis whose step is wanted (2 for a `Scan`'s affine).

    Returns
    -------
    float
        The plane spacing in mm (> 0).

    Raises
    ------
    InputError
        If the affine is not 4x4, not finite, or singular.

    Examples
    --------
    >>> shear = np.array([[1.0, 0, 3, 0], [0, 1, 0, 0], [0, 0, 5, 0], [0, 0, 0, 1]])
    >>> round(slice_plane_spacing_mm(shear), 9)  # the column has length 5.83
    5.0
    """
    lin = _linear_part(affine)
    if slice_axis not in (0, 1, 2):
        raise InputError(f"slice_axis must be 0, 1 or 2, got {slice_axis!r}")
    a, b = (k for k in range(3) if k != slice_axis)
    normal = np.cross(lin[:, a], lin[:, b])
    column = lin[:, slice_axis]
    length = float(np.linalg.norm(column))
    spacing = abs(float(column @ normal)) / float(np.linalg.norm(normal))
    # Not sheared (to SHEAR_TOL): the column length itself, free of round-off,
    # so an orthogonal grid keeps exactly its stated step.
    return length if length - spacing <= SHEAR_TOL * length else spacing


def in_plane_shear(affine: np.ndarray, slice_axis: int = 2) -> float:
    """How far the two in-plane columns of an affine are from perpendicular.

    Returns ``1 - |c_a x c_b| / (|c_a| |c_b|)`` (0 for perpendicular
    columns; ``1 - sin`` of the angle between them), the relative error of
    ``dx * dy`` as the pixel area.

    Parameters
    ----------
    affine : (4, 4) array_like
        Voxel index -> world mm.
    slice_axis : {0, 1, 2}
        The slice axis; the two others span the slice plane.

    Returns
    -------
    float
        In ``[0, 1)``.
    """
    lin = _linear_part(affine)
    a, b = (k for k in range(3) if k != slice_axis)
    na, nb = np.linalg.norm(lin[:, a]), np.linalg.norm(lin[:, b])
    return float(1.0 - np.linalg.norm(np.cross(lin[:, a], lin[:, b])) / (na * nb))


def _linear_part(affine: np.ndarray) -> np.ndarray:
    aff = np.asarray(affine, dtype=np.float64)
    if aff.shape != (4, 4):
        raise InputError(f"affine must be 4x4, got shape {aff.shape}")
    lin = aff[:3, :3]
    if not np.all(np.isfinite(lin)) or abs(np.linalg.det(lin)) < SINGULAR_DET_TOL:
        raise InputError("affine is singular or not finite")
    return lin


def zyx_index_to_ras(points_zyx: np.ndarray, affine: np.ndarray) -> np.ndarray:
    """Map points given as ``(z, y, x)`` voxel indices to RAS millimetres.

    Parameters
    ----------
    points_zyx : (n, 3) array_like
        Continuous voxel indices in array order ``(z, y, x)``.
    affine : (4, 4) ndarray
        Maps ``(x, y, z, 1)`` to RAS mm (see the module docstring).

    Returns
    -------
    (n, 3) float64 ndarray
        RAS coordinates in millimetres.
    """
    pts = np.asarray(points_zyx, dtype=np.float64).reshape(-1, 3)[:, ::-1]
    aff = np.asarray(affine, dtype=np.float64)
    return pts @ aff[:3, :3].T + aff[:3, 3]


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


def reverse_axes(
    array_zyx: np.ndarray, affine_xyz: np.ndarray, flips: tuple[bool, bool, bool]
) -> tuple[np.ndarray, np.ndarray]:
    """Reverse some axes of a grid, keeping every voxel at its world position.

    Parameters
    ----------
    array_zyx : ndarray, shape (z, y, x)
    affine_xyz : (4, 4) array_like
        Maps ``(x, y, z, 1)`` of ``array_zyx`` to RAS mm.
    flips : tuple of bool
        Which of ``(x, y, z)`` to reverse.

    Returns
    -------
    array : ndarray, shape (z, y, x)
        A view of ``array_zyx`` with those axes reversed.
    affine : (4, 4) ndarray
        Its affine: a reversed axis' column negated and the origin moved to
        that axis' last voxel.
    """
    arr = np.asarray(array_zyx)
    aff = np.array(affine_xyz, dtype=np.float64)
    for k, flipped in enumerate(flips):
        if flipped:
            arr = np.flip(arr, 2 - k)
            aff[:3, 3] += aff[:3, k] * (arr.shape[2 - k] - 1)
            aff[:3, k] = -aff[:3, k]
    return arr, aff


def canonical_flips(affine: np.ndarray) -> tuple[bool, bool, bool]:
    """Which Scan axes ``(x, y, z)`` run against the working orientation.

    Each axis is judged by the RAS direction its affine column is closest to
    (the largest absolute component; a tie goes to the first of R, A, S): an
    axis along left-right should run towards the left, one along front-back
    towards posterior, and one along superior-inferior towards inferior in
    the slice plane (rows run top to bottom) and towards superior across
    slices. For an axial head that is LPS, the order of DICOM and of the
    BraTS volumes.

    Parameters
    ----------
    affine : (4, 4) array_like
        Maps the Scan's ``(x, y, z, 1)`` to RAS mm.

    Returns
    -------
    tuple of bool
        ``True`` where that axis should be reversed.

    Examples
    --------
    >>> canonical_flips(np.diag([-1.0, -1.0, 5.0, 1.0]))  # LPS
    (False, False, False)
    >>> canonical_flips(np.diag([-1.0, 1.0, -5.0, 1.0]))  # LAI
    (False, True, True)
    >>> canonical_flips(np.eye(4)[:, [0, 2, 1, 3]])  # coronal RSA: x to R, rows to S
    (True, True, True)
    """
    cols = np.asarray(affine, dtype=np.float64)[:3, :3]
    units = cols / np.linalg.norm(cols, axis=0)
    flips = []
    for k in range(3):
        u = units[:, k]
        d = int(np.argmax(np.round(np.abs(u), 9)))
        wanted = 1.0 if (d == 2 and k == 2) else -1.0  # S across slices; L, P, I otherwise
        flips.append(bool(u[d] * wanted < 0))
    return flips[0], flips[1], flips[2]


def canonical_orientation(scan: Scan) -> Scan:
    """The same scan with its axes run as the working orientation (see the module docstring).

    Axes are only reversed (:func:`canonical_flips`); voxels keep their values
    and world positions, and the source grid records the reversal, so outputs
    are still written in the input's own voxel order. A scan already in the
    working orientation is returned as it is.
    """
    flips = canonical_flips(scan.affine)
    if not any(flips):
        return scan
    image, affine = reverse_axes(scan.image, scan.affine, flips)
    grid = scan.source_grid
    combined = tuple(a != b for a, b in zip(grid.flips, flips, strict=True))
    return replace(
        scan,
        image=np.ascontiguousarray(image),
        affine=affine,
        source_grid=replace(grid, flips=combined),
    )


def slice_order_note(grid: SourceGrid) -> str | None:
    """A note for a file that stores its slices the other way round (None otherwise).

    The notes, the report and ``slices.parquet``'s ``slice_index`` count slices in the
    working order (inferior to superior on an axial stack); such a file, and a viewer
    showing it, counts them from the other end.

    >>> flipped = SourceGrid(shape=(4, 4, 31), affine=np.eye(4), flips=(False, False, True))
    >>> slice_order_note(flipped)[:60]
    'slice numbers count from the other end of the file: it store'
    >>> slice_order_note(SourceGrid(shape=(4, 4, 31), affine=np.eye(4))) is None
    True
    """
    if not grid.flips[2]:
        return None
    last = grid.shape[grid.axes[2]] - 1
    return (
        "slice numbers count from the other end of the file: it stores its slices the other "
        f"way round (slice k here is the file's slice {last} - k; slices.parquet has both)"
    )
