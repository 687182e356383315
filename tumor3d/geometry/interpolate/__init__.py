"""Inter-slice interpolation of tumour masks (spec section 4, Algorithm 1).

Thick-slice MR leaves gaps of several millimetres between the acquired
slices. This module inserts ``m`` synthetic masks between every pair of
consecutive abnormal slices so that the stacked volume has near-isotropic
voxels before marching cubes. The distance transforms live in
:mod:`tumor3d.geometry.distance`.

Methods
-------
``"enhanced"`` (SE)
    The paper's enhanced shape-based interpolation (Algorithm 1): align both
    masks on a common centre, interpolate their chamfer signed distance
    maps (weights 1 and sqrt(2), [Bor86]) linearly, threshold at zero and
    move the result to the linearly interpolated centroid. With
    ``parts="whole"`` this is Algorithm 1 exactly (``configs/paper.yaml``).
``"enhanced-edt"`` (SE-EDT)
    The same with the exact Euclidean distance transform in mm
    (:func:`tumor3d.geometry.distance.euclidean_distance_mm`). The exact EDT is O(N)
    [MQR03], so the paper's O(N^2) for interpolation (Table 5, [A29]) is
    wrong for both transforms.
``"shape"`` (SO)
    The original shape-based method ([RU90], [HZB92]): city-block signed
    distances, no alignment.
``"shape-edt"``
    Shape-based with the exact Euclidean distance in mm, no alignment.
``"linear"`` (LG, mask variant)
    Linear interpolation of the 0/1 masks thresholded at 1/2 ([A14]). The
    gray-level variant the paper means by LG interpolates the preprocessed
    images (:func:`interpolate_gray_slices`) and segments the interpolated
    slices with section 3.

The default, ``"shape-edt"`` with ``parts="matched"``, is the method that
measured best on real expert labels (``reports/interpolation.md``, made by
``benchmarks/interpolation_eval.py``): BraTS whole-tumour labels kept every
5th slice (2 mm thick) and reconstructed to 1 mm. Its 3-D Dice ties with SO
and whole-slice SO-EDT (within two paired standard errors; 0.943-0.976) and
it has the smallest volume error of the three (-0.5 to -1.3 %); SE, the
paper's method, gives 0.927-0.974: centroid alignment hurts real tumours,
whose parts and lobes do not move with the slice centroid. On phantoms with
a synthetic drift SE does better than SO, as the paper reports.

Several tumour parts on one slice (``parts="matched"``)
-------------------------------------------------------
The paper aligns whole slices on the centroid of all their tumour pixels; a
second part moves that centroid, so each part is shifted by the wrong
amount. With ``parts="matched"`` each slice is split into its 8-connected
parts; a part of slice ``a`` and one of slice ``b`` are matched when they
overlap in place or, for the aligned methods, after the whole-slice centroid
alignment of Algorithm 1. Matched parts form groups (the connected
components of the overlap graph, so a part that splits into two is one
group); each group is interpolated on its own, aligned on its own centroids
for the aligned methods. A part without a match shrinks to nothing between
the slices like an end cap: ``{d >= t (max d + h/2)}`` of its own signed
distance ``d`` (a cone). The result is the union over groups. ``"linear"``
is per pixel and ignores ``parts``.

Geometry
--------
Shifts are done on the unbounded pixel plane, and only the output is cut
to the image grid (zero fill, never a wrap-around roll). The distance maps
are computed on the bounding box of the two (aligned) pixel sets only. This
is exact, not an approximation: a pixel outside both masks has ``d_a <=
-h/2`` and ``d_b <= -h/2``, hence ``d_t < 0``, so the interpolated region
``R'`` always lies inside the union of the two masks. On that box the inside
transform is exact because every pixel beyond the box is outside the
object, and the outside transform is exact because the nearest object pixel
lies in the box and the shortest path to it can be chosen inside the
rectangle spanned by the two pixels. For ``"enhanced"`` with ``parts="whole"``
the result equals the literal reading of Algorithm 1 on the image grid
(shift by ``round(C - C_s)`` with zero fill on the grid) whenever that
literal shift clips nothing, and is better when it would clip part of an
object far from the centre.

References
----------
.. [P] V. P. Arakeri and G. R. M. Reddy, "3D reconstruction of brain tumor
   and volume estimation from MR images", IJSIP 6(3), 2013.
.. [Bor86] G. Borgefors, "Distance transformations in digital images",
   Comput. Vis. Graph. Image Process. 34(3):344-371, 1986.
   doi:10.1016/S0734-189X(86)80047-0
.. [RU90] S. P. Raya and J. K. Udupa, "Shape-based interpolation of
   multidimensional objects", IEEE TMI 9(1):32-42, 1990. doi:10.1109/42.52980
.. [HZB92] G. T. Herman, J. Zheng and C. A. Bucholtz, "Shape-based
   interpolation", IEEE CG&A 12(3):69-79, 1992. doi:10.1109/38.135915
.. [MQR03] C. R. Maurer, R. Qi and V. Raghavan, "A linear time algorithm for
   computing exact Euclidean distance transforms of binary images in
   arbitrary dimensions", IEEE TPAMI 25(2):265-270, 2003.
   doi:10.1109/TPAMI.2003.1177156

The package holds the parts by concept: :mod:`~tumor3d.geometry.interpolate.methods`
(methods, parts modes, parameter checks), :mod:`~tumor3d.geometry.interpolate.pair`
(Algorithm 1 between two slices), :mod:`~tumor3d.geometry.interpolate.stack` (a whole
stack), :mod:`~tumor3d.geometry.interpolate.gray` (the gray-level variant) and
:mod:`~tumor3d.geometry.interpolate.error` (leave-one-out error). The public names are
importable from here.
"""

from __future__ import annotations

from tumor3d.geometry.distance import chamfer_distance, signed_distance
from tumor3d.geometry.interpolate.error import interpolation_error_percent, leave_one_out_error
from tumor3d.geometry.interpolate.gray import interpolate_gray_slices
from tumor3d.geometry.interpolate.methods import METHODS, Method, Parts
from tumor3d.geometry.interpolate.pair import interpolate_pair
from tumor3d.geometry.interpolate.stack import (
    InterpolatedStack,
    interpolate_stack,
    slices_between_auto,
)

__all__ = [
    "METHODS",
    "InterpolatedStack",
    "Method",
    "Parts",
    "chamfer_distance",
    "interpolate_gray_slices",
    "interpolate_pair",
    "interpolate_stack",
    "interpolation_error_percent",
    "leave_one_out_error",
    "signed_distance",
    "slices_between_auto",
]
