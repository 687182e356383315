"""tumor3d: 3-D reconstruction and volume of brain tumours from thick-slice MR.

The pure algorithmic core of the method of Arakeri & Reddy (2013),
"3D reconstruction of brain tumor and volume estimation from MR images",
IJSIP 6(3). Arrays in, arrays and dataclasses out: nothing in this package
imports Prefect or touches the file system.

Array conventions used throughout:

* image volumes are ``(z, y, x)``: ``z`` is the slice (acquisition) axis,
  ``y`` the row and ``x`` the column of a slice;
* affines are 4x4 and map the voxel index ``(x, y, z, 1)`` (note: the
  reverse of the array axis order, as NIfTI stores it) to RAS millimetres;
* meshes are ``(n, 3) float64`` vertices in RAS millimetres and
  ``(m, 3) int64`` faces, counter-clockwise seen from outside.
"""

__version__ = "0.1.0"
