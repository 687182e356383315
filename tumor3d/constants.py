"""Numerical tolerances and limits shared across tumor3d, in one place.

Modelled on trimesh's ``constants.py``: every tolerance a comparison uses is
named here once, with the reason for its value, so that two modules never
disagree about what "singular" or "the same spacing" means.
"""

from __future__ import annotations

__all__ = [
    "DICOM_DUPLICATE_POSITION_MM",
    "DICOM_IN_PLANE_DRIFT_FRACTION",
    "DICOM_ORIENTATION_TOL",
    "DICOM_PIXEL_SPACING_REL_TOL",
    "DICOM_UNIT_VECTOR_TOL",
    "IN_PLANE_ORTHOGONALITY_TOL",
    "MAX_VOXELS_DEFAULT",
    "REL_TOL",
    "SHEAR_TOL",
    "SINGULAR_DET_TOL",
    "MESSAGE_VALUE_CHARS",
    "YAML_MAX_ALIASES",
    "YAML_MAX_BYTES",
    "YAML_MAX_EXPANDED_NODES",
]

SINGULAR_DET_TOL = 1e-12
"""A 3x3 linear map with ``|det| <`` this (mm^3 per voxel) is singular.

Far below any real voxel volume (1e-3 mm^3 for a 0.1 mm voxel), far above
float64 round-off of a well-conditioned affine."""

REL_TOL = 0.01
"""Relative tolerance (1 %) of every slice-step and spacing comparison.

Scanner-stated spacings are rounded to a few digits; 1 % is well above that
rounding and well below any step a reader could confuse with another."""

IN_PLANE_ORTHOGONALITY_TOL = 1e-4
"""Largest ``1 - sin(angle)`` between a grid's two in-plane axes.

Above it ``dx * dy`` overstates the pixel area by more than 0.01 % (an angle
of about 89.2 degrees), so such an input is refused rather than measured
wrongly; real MR affines are perpendicular to float32 round-off."""

SHEAR_TOL = 1e-6
"""Relative shear below which an affine's slice axis counts as orthogonal to
the slice plane (``1 - plane spacing / column length``): the slice step is
then the column length itself (free of round-off), and only above it do the
readers mention the shear in ``Scan.source``. A volume error of 1e-6 is far
below anything measurable."""

DICOM_UNIT_VECTOR_TOL = 1e-2
"""ImageOrientationPatient: allowed deviation of each direction cosine vector
from unit length, and of their dot product from 0."""

DICOM_ORIENTATION_TOL = 1e-3
"""Largest difference of an ImageOrientationPatient component between two
slices of one series."""

DICOM_PIXEL_SPACING_REL_TOL = 1e-3
"""Largest relative difference of PixelSpacing between two slices of a series."""

DICOM_DUPLICATE_POSITION_MM = 1e-3
"""Two slices closer than this along the slice normal are at the same position."""

DICOM_IN_PLANE_DRIFT_FRACTION = 0.1
"""Largest in-plane drift of slice positions (gantry tilt), as a fraction of
the smaller pixel spacing, that is still read as an orthogonal stack."""

MAX_VOXELS_DEFAULT = 512_000_000
"""Default limit on the voxel count a volume's header may declare before it is
read (512 million: about 2 GB as float32, far above any MR series)."""

YAML_MAX_ALIASES = 100
"""Largest number of alias (``*name``) uses a YAML document may contain.

A configuration or sidecar needs none; 100 leaves room for hand-written
reuse."""

YAML_MAX_EXPANDED_NODES = 100_000
"""Largest number of nodes a YAML document may have once its aliases are
expanded. Nested anchors ("billion laughs") stay under any alias-count bound
(9 levels of 9 aliases expand 81 aliases into 387 million values), so the
expanded size is bounded too. A configuration has tens of nodes, a stack
sidecar's ``order`` one per slice."""

YAML_MAX_BYTES = 1_000_000
"""Largest YAML text (characters) read as a configuration or sidecar."""

MESSAGE_VALUE_CHARS = 80
"""Longest rendering of a user-supplied value inside an error message."""
