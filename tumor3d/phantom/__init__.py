"""Synthetic head phantoms with a tumour of exactly known volume.

:func:`make_phantom_patient` builds a thick-slice axial MR acquisition of a
smooth synthetic head (scalp, skull, CSF, grey and white matter, two
ventricles) holding a smooth irregular tumour whose centroid drifts from
slice to slice, together with the ground truth: the tumour cross-section on
every acquired slice, the tumour on a fine grid, the tissue label of every
pixel, and the tumour's volume, exact to quadrature precision (~1e-12).

Geometry
--------
All geometry is defined in RAS millimetres around the head centre, RAS
``(0, 0, 0)``.

*Head.* With ``q = (p - c) / a`` (per-axis semi-axes ``a``) and a smooth
"wobble" polynomial ``w`` of degree 1-3 evaluated on ``q`` projected onto the
ball ``|q| <= 1.2``, the normalised head radius is
``rho_h(p) = |q| - w_h(q)`` and the normalised brain radius
``rho_b(p) = rho_h(p) - w_b(q)``. With ``a_ref = min(a)`` the layers are

=============  ============================================================
label          region
=============  ============================================================
0 background   ``rho_h >= 1``
1 scalp        ``1 - t_scalp / a_ref <= rho_h < 1``
2 skull        ``1 - (t_scalp + t_skull) / a_ref <= rho_h < ...``
3 CSF rim      ``rho_h < ...`` and ``rho_b >= 1 - (t_scalp+t_skull+t_csf)/a_ref``
4 grey matter  ``1 - (... + t_gm) / a_ref <= rho_b < ...``
5 white matter inside; two ventricle ellipsoids there are CSF (3)
6 tumour       overrides every other label
=============  ============================================================

Because the skull is a band of the continuous field ``rho_h``, every path
from the brain to the scalp crosses it, on every slice. ``rho_h`` and
``rho_b`` have rigorous Lipschitz bounds (``|grad |q|| <= 1 / min(a)`` and
``|grad w| <= sum_m |c_m| deg_m 1.2**(deg_m - 1)``), which the renderer uses
to skip the supersampling of pixels far from every tissue boundary; near a
boundary, a second-order bound over the pixel's own sample box (the gradient at its
centre plus a Hessian bound, ``raster._fields_pure_near``) skips those the boundary
passes by.

*Tumour* (:class:`TumorShape`). A star-shaped body around the origin,
``r(u) = R0 (1 + sum_i a_i exp(kappa_i (u . d_i - 1)))`` for unit
directions ``u``, mapped by an invertible linear map ``A``, then by the
z-dependent in-plane shear ``p -> p + (s_x(p_z), s_y(p_z), 0)`` (unit
Jacobian, so it moves the centroid of each axial cross-section without
changing the volume), then translated to ``t``. Its volume is

``V = |det A| * (1/3) * integral over S^2 of r(u)^3 dOmega``

computed with Gauss-Legendre quadrature in ``cos(theta)`` and the
(spectrally accurate) periodic trapezoidal rule in ``phi``
(:func:`tumor_volume_mm3`).

Image formation
---------------
Each pixel is the mean tissue intensity over ``n x n`` in-plane sub-samples
and ``m`` samples through the slice thickness (partial-volume edges), times
a smooth multiplicative bias field ``1 + strength * g(p)`` with ``g`` a
random quadratic polynomial normalised to ``max |g| = 1`` over the head,
plus Rician noise: ``sqrt((I + sigma n1)^2 + (sigma n2)^2)`` with
``n1, n2 ~ N(0, 1)`` and ``sigma = noise_fraction * max(I)``
(Gudbjartsson & Patz 1995, doi:10.1002/mrm.1910340618).

The tissue intensities follow T2 (WM < GM < tumour < CSF, fat-bright scalp,
dark skull) or FLAIR (dark CSF, brightest tumour), as in the non-contrast
T2 data of Arakeri & Reddy (2013), IJSIP 6(3).
"""

# The package's modules: shape (analytic tumour), head (head model), raster
# (numba kernels), settings (the arguments checked, presets), patient (assembly).
# The private names are re-exported for the tests that check the kernels against
# reference implementations.
from tumor3d.phantom.head import _Head, _random_head  # noqa: F401
from tumor3d.phantom.patient import PhantomPatient, make_phantom_patient
from tumor3d.phantom.raster import (  # noqa: F401
    _MONOMIALS,
    LABEL_NAMES,
    TISSUE_INTENSITIES,
    _head_fields_many,
    _render,
)
from tumor3d.phantom.shape import TumorShape, random_tumor_shape, tumor_volume_mm3

__all__ = [
    "LABEL_NAMES",
    "PhantomPatient",
    "TISSUE_INTENSITIES",
    "TumorShape",
    "make_phantom_patient",
    "random_tumor_shape",
    "tumor_volume_mm3",
]
