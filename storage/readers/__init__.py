"""Input readers: a NIfTI/NRRD/MetaImage file, a DICOM series or 2-D images -> `Scan`.

The package's modules: :mod:`~tumor3d.storage.readers.common` (shared checks and the
volume geometry rules), :mod:`~tumor3d.storage.readers.nifti`,
:mod:`~tumor3d.storage.readers.itk` (NRRD, MetaImage), :mod:`~tumor3d.storage.readers.dicom`,
:mod:`~tumor3d.storage.readers.stack`; every public name is importable from here.

:func:`read_scan` is the one entry point. It takes one
:class:`~tumor3d.storage.readers.options.ReadOptions` (validated where the
user's input entered) and dispatches on what ``path`` is, through the
registry of formats (:mod:`~tumor3d.storage.readers.registry`: a new format
is one registration):

* a ``.nii`` / ``.nii.gz`` file -> :func:`read_nifti_scan`;
* a ``.nrrd`` / ``.nhdr`` / ``.mha`` / ``.mhd`` file -> :func:`read_itk_scan`
  (SimpleITK; LPS converted to RAS, the same slice-axis rule as NIfTI);
* a folder holding a ``stack.yaml`` (or ``slices.yaml``) sidecar ->
  :func:`read_image_stack` (2-D PNG/TIFF/JPEG slices);
* any other folder -> :func:`read_dicom_series` (one DICOM series).

Every reader returns a :class:`tumor3d.imaging.scan.Scan`: a float32 ``(z, y, x)``
image with ``z`` the slice axis, an affine mapping the voxel index
``(x, y, z, 1)`` to RAS mm, and a :class:`tumor3d.imaging.scan.SourceGrid` that
writes Scan-grid arrays back in the input's own voxel grid.

Slice axis of a NIfTI, NRRD or MetaImage volume (the one rule)
--------------------------------------------------------------
The voxel spacings are the norms of the affine's first three columns. The
voxel axis with the **coarsest spacing** is the slice axis. When several axes
are within 1 % of the coarsest spacing (e.g. an isotropic 1 mm volume), the
one among them whose direction is **closest to superior-inferior** (largest
``|S|`` component of its unit affine column) is chosen, i.e. axial; an exact
tie goes to the highest voxel axis. The voxel axes are permuted (never
resampled) so that the slice axis becomes ``z``; of the two other axes, ``x``
is the one closer to left-right (then to front-back). Then the axes that run
against the working orientation are reversed: ``x`` to the patient's left,
rows to posterior (inferior on a coronal or sagittal slice), slices to
superior; LPS for an axial stack, as DICOM and BraTS store it
(:func:`tumor3d.imaging.scan.canonical_flips`; ``Scan.source`` ends with, for
example, ``stored LAS, read as LPS``). So a file storing the same slices
transposed, mirrored or from the top down gives the same stack (DICOM series
too), and outputs are written back in the file's own order.
See :func:`choose_slice_axis` and :func:`in_plane_axes`.
The two in-plane axes must be perpendicular; the slice step is the distance
between slice planes, ``|det A| / |c_x x c_y|``, which on a sheared grid is
less than the slice-axis column's length
(:func:`tumor3d.imaging.scan.slice_plane_spacing_mm`).

Slice thickness and gap
-----------------------
``slice_step_mm`` (centre to centre) always comes from the geometry (the
affine, the DICOM positions, or thickness + gap for an image stack). The
nominal thickness comes from, in this order: the ``slice_thickness_mm``
argument; the file (the BIDS JSON sidecar's ``SliceThickness`` beside a NIfTI
file, ``x.nii.gz`` -> ``x.json``; DICOM ``SliceThickness``; the stack
sidecar); else it equals the step. The gap is ``step - thickness`` unless
``slice_gap_mm`` is given, in which case thickness + gap must equal the step
within 1 % (an ``InputError`` otherwise); if the thickness is not known at
all it is then ``step - gap``. A thickness above the step, from whichever
source, is overlapping slices (a negative gap, said in the run's notes); one
given by hand more than twice the step is refused as a typo.

DICOM geometry
--------------
Slices are sorted by ``ImagePositionPatient`` projected on the slice normal
``n = r x c`` (``r = IOP[0:3]``, the direction of increasing column index;
``c = IOP[3:6]``, of increasing row index), never by file name or
``InstanceNumber``. The affine, in LPS, has columns ``r * PixelSpacing[1]``
(x = column index), ``c * PixelSpacing[0]`` (y = row index), ``n * step``
(z = sorted slice index) and origin the first sorted slice's position; its
first two rows are negated to give RAS (DICOM PS3.3 C.7.6.2.1.1). A
gantry-tilted stack (positions drifting within the slice plane by more than
0.1 pixel, but along a straight line) keeps its geometry: the z column is the
mean position step ``(p_last - p_first) / (n - 1)``, not perpendicular to the
slices, and ``slice_step_mm`` is still the distance between slice planes.

Image stack convention
----------------------
2-D slices carry no patient geometry, so a display convention is used:
increasing column index points to the patient's left, increasing row index
to posterior and increasing slice index (the sidecar's ``order``, or the
natural sort of the file names) to superior, i.e. the affine is
``diag(-dx, -dy, step, 1)`` with ``step = thickness + gap`` and origin 0.

Protected health information
----------------------------
Patient ids come from the caller or from the file/folder name, never from
DICOM ``PatientName``/``PatientID``; ``Scan.source`` holds only the reader
kind, the file or folder name and the number of slices.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from tumor3d.errors import InputError, os_error_path, os_error_text
from tumor3d.imaging.identity import MODALITIES
from tumor3d.imaging.scan import Scan
from tumor3d.storage.readers.common import (
    MAX_VOXELS_DEFAULT,
    REL_TOL,
    check_field_of_view,
    check_modality,
    choose_slice_axis,
    derive_patient_id,
    in_plane_axes,
    suggest_patient_id,
)
from tumor3d.storage.readers.dicom import read_dicom_series
from tumor3d.storage.readers.itk import ITK_SUFFIXES, read_itk_scan
from tumor3d.storage.readers.nifti import read_nifti_scan
from tumor3d.storage.readers.options import ReadOptions
from tumor3d.storage.readers.registry import read_with_registry, registered_readers
from tumor3d.storage.readers.stack import (
    IMAGE_STACK_SUFFIXES,
    STACK_SIDECAR_NAMES,
    declared_modality,
    read_image_stack,
)

__all__ = [
    "IMAGE_STACK_SUFFIXES",
    "ITK_SUFFIXES",
    "DEFAULT_MODALITY",
    "MAX_VOXELS_DEFAULT",
    "MODALITIES",
    "REL_TOL",
    "STACK_SIDECAR_NAMES",
    "ReadOptions",
    "check_modality",
    "choose_slice_axis",
    "declared_modality",
    "derive_patient_id",
    "in_plane_axes",
    "read_dicom_series",
    "read_image_stack",
    "read_itk_scan",
    "read_nifti_scan",
    "read_scan",
    "registered_readers",
    "resolve_modality",
    "suggest_patient_id",
]

#: The modality a read takes when none is given and the input names none (said on the
#: console by ``tumor3d run``: it decides the segmentation method).
DEFAULT_MODALITY = "t2"


def resolve_modality(path: str | os.PathLike[str], modality: str | None) -> tuple[str, str]:
    """The modality of a read and where it came from.

    ``"given"``: the ``modality`` option (checked); ``"input"``: an image stack's
    sidecar names it (:func:`declared_modality`); ``"default"``: neither,
    :data:`DEFAULT_MODALITY`.

    Raises
    ------
    InputError
        An unknown modality, or a sidecar that cannot be read (naming it).

    Examples
    --------
    >>> resolve_modality("scan.nii.gz", "FLAIR"), resolve_modality("scan.nii.gz", None)
    (('flair', 'given'), ('t2', 'default'))
    """
    if modality is not None:
        return check_modality(modality), "given"
    declared = declared_modality(path)
    if declared is not None:
        return declared, "input"
    return DEFAULT_MODALITY, "default"


def read_scan(
    path: str | os.PathLike[str], options: ReadOptions | None = None, **keywords: Any
) -> Scan:
    """Read one patient's slice stack from a file or a folder, with the registered reader.

    Parameters
    ----------
    path : str or path-like
        A ``.nii``/``.nii.gz`` file, an NRRD/MetaImage file (``.nrrd``,
        ``.nhdr``, ``.mha``, ``.mhd``), a DICOM series folder, or a folder
        of 2-D PNG/TIFF/JPEG slices with a ``stack.yaml`` sidecar: the
        formats of :func:`~tumor3d.storage.readers.registry.registered_readers`.
    options : ReadOptions, optional
        How to read it (validated once where the user's input entered).
    **keywords
        Or the fields of :class:`ReadOptions` as keywords (not both):
        ``modality`` (``None`` means ``"t2"``, except for an image stack
        whose sidecar names a modality), ``patient_id`` (default
        :func:`derive_patient_id` of ``path``), ``series_uid`` (the DICOM
        series to pick when a folder holds several), ``slice_thickness_mm``
        and ``slice_gap_mm`` (override what the input states, see the module
        docstring), ``skip_unreadable`` (DICOM: skip files that cannot be
        read, named in ``Scan.skipped_files``, see :func:`read_dicom_series`),
        ``max_voxels`` (refuse a volume whose header declares more voxels,
        before reading it; default :data:`tumor3d.constants.MAX_VOXELS_DEFAULT`,
        512 million).

    Returns
    -------
    Scan
        float32 ``(z, y, x)`` image with its geometry and source grid.

    Raises
    ------
    InputError
        If the path is missing, unsupported or unreadable, holds a single
        2-D image, a constant volume or non-finite values, spans more than any
        MR scanner images (:func:`tumor3d.storage.readers.common.check_field_of_view`),
        or if an option is invalid. The message names the file and the problem; operating-
        system errors (permissions, I/O) are mapped to one such line.
    """
    if options is None:
        options = ReadOptions(**keywords)
    elif keywords:
        raise TypeError("give read_scan the options as a ReadOptions or as keywords, not both")
    elif not isinstance(options, ReadOptions):
        raise TypeError(f"options must be a ReadOptions, got {type(options).__name__}")
    p = Path(path)
    try:
        scan = _read_scan(p, options)
    except OSError as exc:  # permissions, a vanished mount, an I/O error: one line
        raise InputError(
            f"cannot read the input ({os_error_text(exc)})", os_error_path(exc, p)
        ) from None
    check_field_of_view(scan.image.shape, scan.pixel_spacing_mm, scan.slice_step_mm, str(p))
    return scan


def _read_scan(p: Path, options: ReadOptions) -> Scan:
    if not p.exists():
        raise InputError("no such file or folder", str(p))
    if options.patient_id is None:
        options = options.model_copy(update={"patient_id": derive_patient_id(p)})
    return read_with_registry(p, options)
