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
to skip the supersampling of pixels far from every tissue boundary.

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

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numba
import numpy as np

from tumor3d.errors import InputError
from tumor3d.scan import Scan, SourceGrid, validate_patient_id

__all__ = [
    "LABEL_NAMES",
    "PhantomPatient",
    "TISSUE_INTENSITIES",
    "TumorShape",
    "make_phantom_patient",
    "random_tumor_shape",
    "tumor_volume_mm3",
]

#: Tissue label values of :attr:`PhantomPatient.tissue_labels`.
LABEL_NAMES: dict[int, str] = {
    0: "background",
    1: "scalp",
    2: "skull",
    3: "csf",
    4: "grey_matter",
    5: "white_matter",
    6: "tumour",
}
_BG, _SCALP, _SKULL, _CSF, _GM, _WM, _TUMOR = range(7)

#: Noise-free tissue intensities (arbitrary units, max ~1000), indexed by label.
TISSUE_INTENSITIES: dict[str, tuple[float, ...]] = {
    #        bg    scalp  skull  CSF    GM     WM     tumour
    "t2": (0.0, 600.0, 50.0, 950.0, 450.0, 300.0, 700.0),
    "flair": (0.0, 550.0, 50.0, 100.0, 450.0, 330.0, 850.0),
}

# Presets: in-plane matrix (rows, columns) and pixel spacing in mm.
_PRESETS: dict[str, tuple[tuple[int, int], float]] = {
    "default": ((256, 256), 0.9375),  # 240 x 240 mm
    "paper": ((480, 640), 0.45),  # 216 mm (rows, A-P) x 288 mm (columns, L-R)
}

# Monomials q_x^i q_y^j q_z^k of degree 1..3 used by the wobble polynomials.
_MONOMIALS = np.array(
    [(i, j, k) for i in range(4) for j in range(4) for k in range(4) if 1 <= i + j + k <= 3],
    dtype=np.int64,
)
_WOBBLE_BALL = 1.2  # wobble is evaluated on q projected onto |q| <= 1.2
_BLOCK = 8  # pixel block size of the renderer's uniform-block test

# Nominal layer thicknesses (mm) and shape ranges.
_HEAD_WOBBLE_MM = 5.0
_BRAIN_WOBBLE_MM = 0.8
_T_CSF_MM = 2.0
_T_GM_MM = 3.0


# ---------------------------------------------------------------------------
# Tumour shape
# ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class TumorShape:
    """A smooth star-shaped tumour body, linearly mapped, sheared and translated.

    A point ``P`` (RAS mm) is inside iff, with ``v = P - center`` and
    ``v' = v - (s_x(v_z), s_y(v_z), 0)`` and ``w = A^-1 v'``,
    ``|w| <= r(w / |w|)`` where
    ``r(u) = R0 (1 + sum_i a_i exp(kappa_i (u . d_i - 1)))``
    and ``s_x(z) = sum_k shear[0, k] z^(k+1)`` (likewise ``s_y``).

    Parameters
    ----------
    center_mm : (3,) array_like
        Translation ``t`` in RAS mm.
    radius_mm : float
        Base radius ``R0`` (mm), > 0.
    bump_directions : (n, 3) array_like
        Bump directions ``d_i``; normalised to unit length.
    bump_amplitudes : (n,) array_like
        Relative bump amplitudes ``a_i``; the negative ones must sum to
        more than -1 so that ``r(u) > 0`` everywhere.
    bump_kappas : (n,) array_like
        Bump concentrations ``kappa_i >= 0`` (larger is narrower).
    linear_map : (3, 3) array_like
        The invertible matrix ``A``.
    shear_coefficients : (2, k) array_like
        Polynomial coefficients of ``s_x`` (row 0) and ``s_y`` (row 1) in
        powers ``z, z^2, ..., z^k`` of the body's local ``z`` (mm).

    All arrays are copied and made read-only.
    """

    center_mm: np.ndarray
    radius_mm: float
    bump_directions: np.ndarray
    bump_amplitudes: np.ndarray
    bump_kappas: np.ndarray
    linear_map: np.ndarray
    shear_coefficients: np.ndarray

    def __post_init__(self) -> None:
        center = np.array(self.center_mm, dtype=np.float64).reshape(-1)
        if center.shape != (3,) or not np.all(np.isfinite(center)):
            raise InputError(f"center_mm must be 3 finite numbers, got {self.center_mm!r}")
        radius = float(self.radius_mm)
        if not (np.isfinite(radius) and radius > 0):
            raise InputError(f"radius_mm must be a positive number, got {self.radius_mm!r}")
        dirs = np.array(self.bump_directions, dtype=np.float64).reshape(-1, 3)
        amps = np.array(self.bump_amplitudes, dtype=np.float64).reshape(-1)
        kappas = np.array(self.bump_kappas, dtype=np.float64).reshape(-1)
        if not (len(dirs) == len(amps) == len(kappas)):
            raise InputError(
                "bump_directions, bump_amplitudes and bump_kappas must have the same "
                f"length, got {len(dirs)}, {len(amps)} and {len(kappas)}"
            )
        norms = np.linalg.norm(dirs, axis=1)
        if np.any(~np.isfinite(norms)) or np.any(norms == 0):
            raise InputError("bump_directions must be finite non-zero vectors")
        dirs = dirs / norms[:, None]
        if not (np.all(np.isfinite(amps)) and np.all(np.isfinite(kappas))):
            raise InputError("bump amplitudes and kappas must be finite")
        if np.any(kappas < 0):
            raise InputError(f"bump_kappas must be >= 0, got {kappas.tolist()}")
        if 1.0 + amps[amps < 0].sum() <= 0:
            raise InputError(
                "the negative bump_amplitudes must sum to more than -1 so that r(u) > 0, "
                f"got {amps[amps < 0].sum():.3g}"
            )
        lin = np.array(self.linear_map, dtype=np.float64)
        if lin.shape != (3, 3) or not np.all(np.isfinite(lin)):
            raise InputError(f"linear_map must be a finite 3x3 matrix, got shape {lin.shape}")
        if abs(np.linalg.det(lin)) < 1e-12:
            raise InputError("linear_map must be invertible (|det| > 1e-12)")
        shear = np.array(self.shear_coefficients, dtype=np.float64)
        if shear.ndim != 2 or shear.shape[0] != 2 or not np.all(np.isfinite(shear)):
            raise InputError(
                f"shear_coefficients must be a finite (2, k) array, got shape {shear.shape}"
            )
        if np.any(shear[:, 3:] != 0):
            raise InputError("shear_coefficients: polynomials above degree 3 are not supported")
        for name, arr in (
            ("center_mm", center),
            ("bump_directions", dirs),
            ("bump_amplitudes", amps),
            ("bump_kappas", kappas),
            ("linear_map", lin),
            ("shear_coefficients", shear),
        ):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "radius_mm", radius)

    @classmethod
    def sphere(cls, center_mm: Any, radius_mm: float) -> TumorShape:
        """Return a ball of radius ``radius_mm`` centred at ``center_mm`` (RAS mm)."""
        return cls(
            center_mm=center_mm,
            radius_mm=radius_mm,
            bump_directions=np.zeros((0, 3)),
            bump_amplitudes=np.zeros(0),
            bump_kappas=np.zeros(0),
            linear_map=np.eye(3),
            shear_coefficients=np.zeros((2, 1)),
        )

    def radius_function(self, directions: np.ndarray) -> np.ndarray:
        """Evaluate ``r(u)`` (mm) for unit direction vectors ``u``, shape ``(n, 3)``."""
        u = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        return _radius_function(
            u, self.radius_mm, self.bump_directions, self.bump_amplitudes, self.bump_kappas
        )

    def contains(self, points_mm: np.ndarray) -> np.ndarray:
        """Inside-test of points.

        Parameters
        ----------
        points_mm : (n, 3) array_like
            RAS coordinates in mm.

        Returns
        -------
        (n,) bool ndarray
            ``True`` where the point lies inside the tumour (boundary included).
        """
        pts = np.ascontiguousarray(np.asarray(points_mm, dtype=np.float64).reshape(-1, 3))
        packed, dirs, amps, kappas = self._packed()
        return _contains_points(pts, packed, dirs, amps, kappas)

    def surface_points(self, n_theta: int = 48, n_phi: int = 96) -> np.ndarray:
        """Points on the tumour surface (RAS mm), ``(n_theta * n_phi, 3)``.

        The surface is the image of ``r(u) u`` on a Gauss-Legendre x uniform
        grid of directions, mapped by ``A``, the shear and the translation.
        """
        u, _ = _sphere_quadrature(n_theta, n_phi)
        local = u * self.radius_function(u)[:, None]
        return self.map_local(local)

    def map_local(self, local: np.ndarray) -> np.ndarray:
        """Map points of the undeformed star body (mm) to RAS mm: ``A``, shear, translation."""
        p = np.asarray(local, dtype=np.float64).reshape(-1, 3) @ self.linear_map.T
        z = p[:, 2]
        powers = np.stack([z ** (k + 1) for k in range(self.shear_coefficients.shape[1])], axis=1)
        p = p.copy()
        p[:, 0] += powers @ self.shear_coefficients[0]
        p[:, 1] += powers @ self.shear_coefficients[1]
        return p + self.center_mm

    def _packed(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Pack the parameters for the numba kernels (see ``_tumor_inside``)."""
        shear = np.zeros((2, 3))
        k = min(3, self.shear_coefficients.shape[1])
        shear[:, :k] = self.shear_coefficients[:, :k]
        packed = np.concatenate(
            [
                [1.0],
                self.center_mm,
                np.linalg.inv(self.linear_map).ravel(),
                shear.ravel(),
                [self.radius_mm],
            ]
        )
        # writable C-contiguous copies: numba compiles read-only arrays separately
        return (
            packed,
            np.array(self.bump_directions, order="C"),
            np.array(self.bump_amplitudes, order="C"),
            np.array(self.bump_kappas, order="C"),
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-able description of the shape."""
        return {
            "center_mm": self.center_mm.tolist(),
            "radius_mm": self.radius_mm,
            "bump_directions": self.bump_directions.tolist(),
            "bump_amplitudes": self.bump_amplitudes.tolist(),
            "bump_kappas": self.bump_kappas.tolist(),
            "linear_map": self.linear_map.tolist(),
            "shear_coefficients": self.shear_coefficients.tolist(),
        }


def _radius_function(u, radius, dirs, amps, kappas) -> np.ndarray:
    """``r(u) = R0 (1 + sum_i a_i exp(kappa_i (u . d_i - 1)))`` for unit rows of ``u``."""
    if len(amps) == 0:
        return np.full(len(u), radius)
    return radius * (1.0 + np.exp(kappas * (u @ dirs.T - 1.0)) @ amps)


def _sphere_quadrature(n_theta: int, n_phi: int) -> tuple[np.ndarray, np.ndarray]:
    """Directions and weights of a product rule on the unit sphere.

    Gauss-Legendre in ``cos(theta)`` times the periodic trapezoidal rule in
    ``phi``; ``sum(weights) = 4 pi``.
    """
    x, wx = np.polynomial.legendre.leggauss(n_theta)
    phi = 2.0 * np.pi * np.arange(n_phi) / n_phi
    sin_t = np.sqrt(1.0 - x**2)
    u = np.stack(
        [
            np.outer(sin_t, np.cos(phi)).ravel(),
            np.outer(sin_t, np.sin(phi)).ravel(),
            np.repeat(x, n_phi),
        ],
        axis=1,
    )
    weights = np.repeat(wx, n_phi) * (2.0 * np.pi / n_phi)
    return u, weights


def tumor_volume_mm3(shape: TumorShape, *, n_theta: int = 128, n_phi: int = 256) -> float:
    """Exact volume of a :class:`TumorShape` by quadrature.

    ``V = |det A| * (1/3) * integral_{S^2} r(u)^3 dOmega``: the volume of a
    star-shaped body in spherical coordinates, scaled by the linear map; the
    shear has unit Jacobian and the translation changes nothing. The
    integrand is analytic, so the product rule (Gauss-Legendre in
    ``cos(theta)``, trapezoidal in ``phi``) converges exponentially; the
    defaults reach ~1e-14 relative error for the shapes made here.

    Parameters
    ----------
    shape : TumorShape
        The tumour.
    n_theta, n_phi : int
        Quadrature nodes in ``cos(theta)`` (>= 2) and ``phi`` (>= 3).

    Returns
    -------
    float
        Volume in mm^3.

    Raises
    ------
    InputError
        If ``shape`` is not a TumorShape or a node count is too small.

    Examples
    --------
    >>> ball = TumorShape.sphere((0, 0, 0), 10.0)
    >>> round(tumor_volume_mm3(ball) / (4 / 3 * np.pi * 1000.0), 12)
    1.0
    """
    if not isinstance(shape, TumorShape):
        raise InputError(f"shape must be a TumorShape, got {type(shape).__name__}")
    if int(n_theta) < 2 or int(n_phi) < 3:
        raise InputError(f"need n_theta >= 2 and n_phi >= 3, got {n_theta} and {n_phi}")
    u, w = _sphere_quadrature(int(n_theta), int(n_phi))
    r = shape.radius_function(u)
    return float(abs(np.linalg.det(shape.linear_map)) * np.dot(w, r**3) / 3.0)


def random_tumor_shape(
    rng: np.random.Generator,
    *,
    equivalent_diameter_mm: float,
    center_mm: Any = (0.0, 0.0, 0.0),
) -> TumorShape:
    """Draw a random smooth irregular tumour of a given equivalent diameter.

    3-6 bumps (amplitudes in [-0.3, 0.5], concentrations in [2, 6]), a
    volume-preserving symmetric stretch with axis ratios up to ~1.5 along
    random axes, and a shear ``s(z) = R0 ((b1 z/R0 + b2 (z/R0)^2) e_psi +
    b3 (z/R0)^2 e_psi_perp)`` with ``|b1|`` in [0.2, 0.45] (centroid drift
    of 20-45 % of the height), so the shape scales with ``R0``.

    Parameters
    ----------
    rng : numpy.random.Generator
        Source of randomness.
    equivalent_diameter_mm : float
        Diameter of the ball of the same volume, mm (> 0).
    center_mm : (3,) array_like
        Translation (RAS mm).

    Returns
    -------
    TumorShape
    """
    if not isinstance(rng, np.random.Generator):
        raise InputError(f"rng must be a numpy.random.Generator, got {type(rng).__name__}")
    if not (np.isfinite(equivalent_diameter_mm) and equivalent_diameter_mm > 0):
        raise InputError(f"equivalent_diameter_mm must be positive, got {equivalent_diameter_mm!r}")
    n_bumps = int(rng.integers(3, 7))
    dirs = rng.normal(size=(n_bumps, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    amps = rng.uniform(-0.3, 0.5, size=n_bumps)
    neg = amps[amps < 0].sum()
    if neg < -0.6:
        amps[amps < 0] *= -0.6 / neg
    kappas = rng.uniform(2.0, 6.0, size=n_bumps)
    # volume-preserving symmetric stretch along random orthogonal axes
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    alpha = rng.uniform(-0.2, 0.2, size=3)
    alpha -= alpha.mean()
    lin = q @ np.diag(np.exp(alpha)) @ q.T
    psi = rng.uniform(0.0, 2.0 * np.pi)
    b1 = rng.uniform(0.2, 0.45) * rng.choice([-1.0, 1.0])
    b2 = rng.uniform(-0.25, 0.25)
    b3 = rng.uniform(-0.15, 0.15)
    e_par = np.array([np.cos(psi), np.sin(psi)])
    e_perp = np.array([-np.sin(psi), np.cos(psi)])
    # unit-radius shape first, then scale to the requested volume
    unit = TumorShape(
        center_mm=(0.0, 0.0, 0.0),
        radius_mm=1.0,
        bump_directions=dirs,
        bump_amplitudes=amps,
        bump_kappas=kappas,
        linear_map=lin,
        shear_coefficients=np.zeros((2, 1)),
    )
    v1 = tumor_volume_mm3(unit)
    radius = (np.pi * equivalent_diameter_mm**3 / 6.0 / v1) ** (1.0 / 3.0)
    # s(z) = R0 (b1 z/R0 + b2 (z/R0)^2): coefficients of z and z^2
    shear = np.stack([b1 * e_par, (b2 * e_par + b3 * e_perp) / radius], axis=1)
    return TumorShape(
        center_mm=center_mm,
        radius_mm=radius,
        bump_directions=dirs,
        bump_amplitudes=amps,
        bump_kappas=kappas,
        linear_map=lin,
        shear_coefficients=shear,
    )


def _scaled_shape(shape: TumorShape, factor: float, center_mm: np.ndarray) -> TumorShape:
    """Return ``shape`` scaled by ``factor`` about its centre and moved to ``center_mm``."""
    shear = shape.shear_coefficients.copy()
    for k in range(shear.shape[1]):
        shear[:, k] /= factor**k  # s(z) -> factor * s(z / factor)
    return TumorShape(
        center_mm=center_mm,
        radius_mm=shape.radius_mm * factor,
        bump_directions=shape.bump_directions,
        bump_amplitudes=shape.bump_amplitudes,
        bump_kappas=shape.bump_kappas,
        linear_map=shape.linear_map,
        shear_coefficients=shear,
    )


# ---------------------------------------------------------------------------
# numba kernels
# ---------------------------------------------------------------------------
# Packed tumour vector (length 20):
#   [0] has_tumour, [1:4] t, [4:13] A^-1 (row-major), [13:16] s_x coefficients of
#   z, z^2, z^3, [16:19] s_y coefficients, [19] R0.
# Packed head vector (length 13):
#   [0:3] centre c, [3:6] semi-axes a, [6] thr_scalp_outer (=1), [7] thr_skull_outer,
#   [8] thr_brain_outer (on rho_h), [9] thr_csf_inner, [10] thr_gm_inner (on rho_b),
#   [11] Lipschitz of rho_h (1/mm), [12] Lipschitz of rho_b (1/mm).


@numba.njit(cache=True, inline="always", fastmath=True)
def _tumor_inside(x, y, z, tum, dirs, amps, kappas):
    """Inside-test of one RAS point for the packed tumour (see module notes)."""
    if tum[0] == 0.0:
        return False
    vx = x - tum[1]
    vy = y - tum[2]
    vz = z - tum[3]
    sx = vz * (tum[13] + vz * (tum[14] + vz * tum[15]))
    sy = vz * (tum[16] + vz * (tum[17] + vz * tum[18]))
    vx -= sx
    vy -= sy
    wx = tum[4] * vx + tum[5] * vy + tum[6] * vz
    wy = tum[7] * vx + tum[8] * vy + tum[9] * vz
    wz = tum[10] * vx + tum[11] * vy + tum[12] * vz
    n = math.sqrt(wx * wx + wy * wy + wz * wz)
    if n == 0.0:
        return True
    s = 1.0
    for i in range(amps.shape[0]):
        cos_g = (wx * dirs[i, 0] + wy * dirs[i, 1] + wz * dirs[i, 2]) / n
        s += amps[i] * math.exp(kappas[i] * (cos_g - 1.0))
    return n <= tum[19] * s


@numba.njit(cache=True, fastmath=True)
def _contains_points(pts, tum, dirs, amps, kappas):
    out = np.zeros(pts.shape[0], dtype=np.bool_)
    for i in range(pts.shape[0]):
        out[i] = _tumor_inside(pts[i, 0], pts[i, 1], pts[i, 2], tum, dirs, amps, kappas)
    return out


@numba.njit(cache=True, inline="always", fastmath=True)
def _wobbles(qx, qy, qz, ch, cb):
    """Evaluate both wobble polynomials ``sum_m c[m] q^_MONOMIALS[m]``.

    ``q`` is first projected onto the ball ``|q| <= 1.2``. Unrolled for
    speed; the term order is that of ``_MONOMIALS``.
    """
    n = math.sqrt(qx * qx + qy * qy + qz * qz)
    if n > 1.2:
        f = 1.2 / n
        qx *= f
        qy *= f
        qz *= f
    m0 = qz
    m1 = qz * qz
    m2 = qz * qz * qz
    m3 = qy
    m4 = qy * qz
    m5 = qy * qz * qz
    m6 = qy * qy
    m7 = qy * qy * qz
    m8 = qy * qy * qy
    m9 = qx
    m10 = qx * qz
    m11 = qx * qz * qz
    m12 = qx * qy
    m13 = qx * qy * qz
    m14 = qx * qy * qy
    m15 = qx * qx
    m16 = qx * qx * qz
    m17 = qx * qx * qy
    m18 = qx * qx * qx
    wh = (
        ch[0] * m0
        + ch[1] * m1
        + ch[2] * m2
        + ch[3] * m3
        + ch[4] * m4
        + ch[5] * m5
        + ch[6] * m6
        + ch[7] * m7
        + ch[8] * m8
        + ch[9] * m9
        + ch[10] * m10
        + ch[11] * m11
        + ch[12] * m12
        + ch[13] * m13
        + ch[14] * m14
        + ch[15] * m15
        + ch[16] * m16
        + ch[17] * m17
        + ch[18] * m18
    )
    wb = (
        cb[0] * m0
        + cb[1] * m1
        + cb[2] * m2
        + cb[3] * m3
        + cb[4] * m4
        + cb[5] * m5
        + cb[6] * m6
        + cb[7] * m7
        + cb[8] * m8
        + cb[9] * m9
        + cb[10] * m10
        + cb[11] * m11
        + cb[12] * m12
        + cb[13] * m13
        + cb[14] * m14
        + cb[15] * m15
        + cb[16] * m16
        + cb[17] * m17
        + cb[18] * m18
    )
    return wh, wb


@numba.njit(cache=True, inline="always", fastmath=True)
def _head_fields(x, y, z, head, wob_h, wob_b):
    """Normalised head and brain radii ``(rho_h, rho_b)`` at one RAS point."""
    qx = (x - head[0]) / head[3]
    qy = (y - head[1]) / head[4]
    qz = (z - head[2]) / head[5]
    rq = math.sqrt(qx * qx + qy * qy + qz * qz)
    wh, wb = _wobbles(qx, qy, qz, wob_h, wob_b)
    return rq - wh, rq - wh - wb


@numba.njit(cache=True, inline="always", fastmath=True)
def _ventricle_rho(x, y, z, vent, i):
    qx = (x - vent[i, 0]) / vent[i, 3]
    qy = (y - vent[i, 1]) / vent[i, 4]
    qz = (z - vent[i, 2]) / vent[i, 5]
    return math.sqrt(qx * qx + qy * qy + qz * qz)


@numba.njit(cache=True, inline="always", fastmath=True)
def _head_label(x, y, z, rho_h, rho_b, head, vent):
    """Tissue label (0-5) of the head at one RAS point from its fields."""
    if rho_h >= head[6]:
        return _BG
    if rho_h >= head[7]:
        return _SCALP
    if rho_h >= head[8]:
        return _SKULL
    if rho_b >= head[9]:
        return _CSF
    for i in range(vent.shape[0]):
        if _ventricle_rho(x, y, z, vent, i) < 1.0:
            return _CSF
    if rho_b >= head[10]:
        return _GM
    return _WM


@numba.njit(cache=True, inline="always", fastmath=True)
def _box_overlaps(x, y, z, half, bbox):
    """Whether the box ``[x +- half[0]] x [y +- half[1]] x [z +- half[2]]`` meets ``bbox``."""
    return (
        x + half[0] >= bbox[0]
        and x - half[0] <= bbox[3]
        and y + half[1] >= bbox[1]
        and y - half[1] <= bbox[4]
        and z + half[2] >= bbox[2]
        and z - half[2] <= bbox[5]
    )


@numba.njit(cache=True, inline="always", fastmath=True)
def _label_at(x, y, z, head, wob_h, wob_b, vent, tum, dirs, amps, kappas, tum_bbox, zero3):
    """Tissue label (0-6) at one RAS point; the tumour overrides the head."""
    if (
        tum[0] != 0.0
        and _box_overlaps(x, y, z, zero3, tum_bbox)
        and _tumor_inside(x, y, z, tum, dirs, amps, kappas)
    ):
        return _TUMOR
    rho_h, rho_b = _head_fields(x, y, z, head, wob_h, wob_b)
    return _head_label(x, y, z, rho_h, rho_b, head, vent)


@numba.njit(cache=True, inline="always", fastmath=True)
def _is_pure(x, y, z, rho_h, rho_b, half_diag, box, head, vent, tum_bbox):
    """Tell whether one label fills the whole sample box around ``(x, y, z)``.

    No boundary can cross the ball of radius ``half_diag`` (which holds the
    box) when every field is farther from its thresholds than its Lipschitz
    bound times ``half_diag`` (``head[11]`` for ``rho_h``, ``head[12]`` for
    ``rho_b``, ``1 / min(semi-axes)`` for a ventricle's radius); any overlap
    of the box with the tumour's bounding box makes the pixel impure.
    """
    if tum_bbox[0] <= tum_bbox[3] and _box_overlaps(x, y, z, box, tum_bbox):
        return False
    mh = head[11] * half_diag
    for k in range(6, 9):
        if abs(rho_h - head[k]) <= mh:
            return False
    mb = head[12] * half_diag
    for k in range(9, 11):
        if abs(rho_b - head[k]) <= mb:
            return False
    for i in range(vent.shape[0]):
        amin = min(vent[i, 3], min(vent[i, 4], vent[i, 5]))
        if abs(_ventricle_rho(x, y, z, vent, i) - 1.0) <= half_diag / amin:
            return False
    return True


@numba.njit(cache=True, fastmath=True)
def _render(
    aff,
    nz,
    ny,
    nx,
    sub_xy,
    sub_z,
    head,
    wob_h,
    wob_b,
    vent,
    tum,
    dirs,
    amps,
    kappas,
    tum_bbox,
    values,
    adaptive,
):
    """Partial-volume image and centre labels of every slice.

    ``sub_xy`` are in-plane sub-sample offsets (pixel units), ``sub_z`` the
    through-slice offsets (slice-index units); a pixel's value is the mean
    of ``values[label]`` over the ``len(sub_xy)**2 * len(sub_z)`` samples.
    With ``adaptive``, blocks of ``_BLOCK x _BLOCK`` pixels, and then single
    pixels, that :func:`_is_pure` proves uniform get ``values[label]`` at
    once. ``tum_bbox`` (min3, max3) must hold the
    tumour; give ``min > max`` when there is none. Returns
    ``(image float64, labels uint8)``, both ``(nz, ny, nx)``.
    """
    image = np.empty((nz, ny, nx), dtype=np.float64)
    labels = np.empty((nz, ny, nx), dtype=np.uint8)
    zero3 = np.zeros(3)
    mxy = np.max(np.abs(sub_xy))
    mz = np.max(np.abs(sub_z))
    # half extents (mm) of one pixel's sample box and its half diagonal
    box = np.zeros(3)
    for r in range(3):
        box[r] = (abs(aff[r, 0]) + abs(aff[r, 1])) * mxy + abs(aff[r, 2]) * mz
    half_diag = math.sqrt(box[0] ** 2 + box[1] ** 2 + box[2] ** 2)
    bbox = np.zeros(3)
    for k in range(nz):
        for j0 in range(0, ny, _BLOCK):
            j1 = min(j0 + _BLOCK, ny)
            for i0 in range(0, nx, _BLOCK):
                i1 = min(i0 + _BLOCK, nx)
                if adaptive:
                    # whole block uniform? (covers all its pixels' sample boxes)
                    ic = 0.5 * (i0 + i1 - 1)
                    jc = 0.5 * (j0 + j1 - 1)
                    x = aff[0, 0] * ic + aff[0, 1] * jc + aff[0, 2] * k + aff[0, 3]
                    y = aff[1, 0] * ic + aff[1, 1] * jc + aff[1, 2] * k + aff[1, 3]
                    z = aff[2, 0] * ic + aff[2, 1] * jc + aff[2, 2] * k + aff[2, 3]
                    for r in range(3):
                        bbox[r] = (
                            abs(aff[r, 0]) * (0.5 * (i1 - i0 - 1) + mxy)
                            + abs(aff[r, 1]) * (0.5 * (j1 - j0 - 1) + mxy)
                            + abs(aff[r, 2]) * mz
                        )
                    hd = math.sqrt(bbox[0] ** 2 + bbox[1] ** 2 + bbox[2] ** 2)
                    rho_h, rho_b = _head_fields(x, y, z, head, wob_h, wob_b)
                    if _is_pure(x, y, z, rho_h, rho_b, hd, bbox, head, vent, tum_bbox):
                        lab = _head_label(x, y, z, rho_h, rho_b, head, vent)
                        for j in range(j0, j1):
                            for i in range(i0, i1):
                                labels[k, j, i] = lab
                                image[k, j, i] = values[lab]
                        continue
                for j in range(j0, j1):
                    for i in range(i0, i1):
                        lab, val = _render_pixel(
                            aff,
                            k,
                            j,
                            i,
                            sub_xy,
                            sub_z,
                            head,
                            wob_h,
                            wob_b,
                            vent,
                            tum,
                            dirs,
                            amps,
                            kappas,
                            tum_bbox,
                            values,
                            adaptive,
                            half_diag,
                            box,
                            zero3,
                        )
                        labels[k, j, i] = lab
                        image[k, j, i] = val
    return image, labels


@numba.njit(cache=True, inline="always", fastmath=True)
def _render_pixel(
    aff,
    k,
    j,
    i,
    sub_xy,
    sub_z,
    head,
    wob_h,
    wob_b,
    vent,
    tum,
    dirs,
    amps,
    kappas,
    tum_bbox,
    values,
    adaptive,
    half_diag,
    box,
    zero3,
):
    """Centre label and partial-volume value of pixel ``(k, j, i)``."""
    x = aff[0, 0] * i + aff[0, 1] * j + aff[0, 2] * k + aff[0, 3]
    y = aff[1, 0] * i + aff[1, 1] * j + aff[1, 2] * k + aff[1, 3]
    z = aff[2, 0] * i + aff[2, 1] * j + aff[2, 2] * k + aff[2, 3]
    rho_h, rho_b = _head_fields(x, y, z, head, wob_h, wob_b)
    if (
        tum[0] != 0.0
        and _box_overlaps(x, y, z, zero3, tum_bbox)
        and _tumor_inside(x, y, z, tum, dirs, amps, kappas)
    ):
        lab = _TUMOR
    else:
        lab = _head_label(x, y, z, rho_h, rho_b, head, vent)
    if adaptive and _is_pure(x, y, z, rho_h, rho_b, half_diag, box, head, vent, tum_bbox):
        return lab, values[lab]
    acc = 0.0
    for a in range(sub_z.shape[0]):
        kk = k + sub_z[a]
        for b in range(sub_xy.shape[0]):
            jj = j + sub_xy[b]
            for c in range(sub_xy.shape[0]):
                ii = i + sub_xy[c]
                xs = aff[0, 0] * ii + aff[0, 1] * jj + aff[0, 2] * kk + aff[0, 3]
                ys = aff[1, 0] * ii + aff[1, 1] * jj + aff[1, 2] * kk + aff[1, 3]
                zs = aff[2, 0] * ii + aff[2, 1] * jj + aff[2, 2] * kk + aff[2, 3]
                acc += values[
                    _label_at(
                        xs,
                        ys,
                        zs,
                        head,
                        wob_h,
                        wob_b,
                        vent,
                        tum,
                        dirs,
                        amps,
                        kappas,
                        tum_bbox,
                        zero3,
                    )
                ]
    return lab, acc / (sub_xy.shape[0] * sub_xy.shape[0] * sub_z.shape[0])


@numba.njit(cache=True, fastmath=True)
def _mask_in_box(aff, lo, hi, tum, dirs, amps, kappas, out):
    """Fill ``out[k, j, i]`` with the tumour inside-test for indices in ``[lo, hi)``."""
    for k in range(lo[0], hi[0]):
        for j in range(lo[1], hi[1]):
            for i in range(lo[2], hi[2]):
                x = aff[0, 0] * i + aff[0, 1] * j + aff[0, 2] * k + aff[0, 3]
                y = aff[1, 0] * i + aff[1, 1] * j + aff[1, 2] * k + aff[1, 3]
                z = aff[2, 0] * i + aff[2, 1] * j + aff[2, 2] * k + aff[2, 3]
                out[k, j, i] = _tumor_inside(x, y, z, tum, dirs, amps, kappas)


@numba.njit(cache=True, fastmath=True)
def _head_fields_many(pts, head, wob_h, wob_b):
    """``(rho_h, rho_b)`` at each row of ``pts`` (RAS mm), shape ``(n, 2)``."""
    out = np.empty((pts.shape[0], 2))
    for i in range(pts.shape[0]):
        rho_h, rho_b = _head_fields(pts[i, 0], pts[i, 1], pts[i, 2], head, wob_h, wob_b)
        out[i, 0] = rho_h
        out[i, 1] = rho_b
    return out


# ---------------------------------------------------------------------------
# Head model
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class _Head:
    """Random head geometry (all lengths mm)."""

    semi_axes: np.ndarray
    t_scalp: float
    t_skull: float
    wob_h: np.ndarray
    wob_b: np.ndarray
    ventricles: np.ndarray  # (2, 6): centre, semi-axes
    center: np.ndarray = field(default_factory=lambda: np.zeros(3))

    @property
    def a_ref(self) -> float:
        return float(self.semi_axes.min())

    @property
    def extent_mm(self) -> np.ndarray:
        """Half extents of a box around the head's centre that contains the head."""
        return self.semi_axes * (1.0 + _wobble_bound(self.wob_h))

    def thresholds(self) -> np.ndarray:
        a = self.a_ref
        return np.array(
            [
                1.0,
                1.0 - self.t_scalp / a,
                1.0 - (self.t_scalp + self.t_skull) / a,
                1.0 - (self.t_scalp + self.t_skull + _T_CSF_MM) / a,
                1.0 - (self.t_scalp + self.t_skull + _T_CSF_MM + _T_GM_MM) / a,
            ]
        )

    def packed(self) -> np.ndarray:
        lw_h = _wobble_lipschitz(self.wob_h)
        lw_b = _wobble_lipschitz(self.wob_b)
        amin = self.semi_axes.min()
        return np.concatenate(
            [
                self.center,
                self.semi_axes,
                self.thresholds(),
                [(1.0 + lw_h) / amin, (1.0 + lw_h + lw_b) / amin],
            ]
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "center_mm": self.center.tolist(),
            "semi_axes_mm": self.semi_axes.tolist(),
            "scalp_thickness_mm": self.t_scalp,
            "skull_thickness_mm": self.t_skull,
            "csf_rim_thickness_mm": _T_CSF_MM,
            "grey_matter_thickness_mm": _T_GM_MM,
            "head_wobble_coefficients": self.wob_h.tolist(),
            "brain_wobble_coefficients": self.wob_b.tolist(),
            "wobble_monomials": _MONOMIALS.tolist(),
            "ventricles_center_semi_axes_mm": self.ventricles.tolist(),
        }


def _wobble_bound(coef: np.ndarray) -> float:
    """Rigorous bound of ``|w|`` on the ball ``|q| <= 1.2``: ``sum |c_m| 1.2^deg_m``."""
    deg = _MONOMIALS.sum(axis=1)
    return float(np.sum(np.abs(coef) * _WOBBLE_BALL**deg))


def _wobble_lipschitz(coef: np.ndarray) -> float:
    """Rigorous Lipschitz bound of ``w``: ``sum |c_m| deg_m 1.2^(deg_m - 1)``."""
    deg = _MONOMIALS.sum(axis=1)
    return float(np.sum(np.abs(coef) * deg * _WOBBLE_BALL ** (deg - 1)))


def _random_wobble(rng: np.random.Generator, bound: float) -> np.ndarray:
    """Random wobble coefficients scaled so that ``_wobble_bound == bound``."""
    deg = _MONOMIALS.sum(axis=1)
    coef = rng.normal(size=len(_MONOMIALS)) / deg  # favour the lowest frequencies
    return coef * (bound / _wobble_bound(coef))


def _random_head(rng: np.random.Generator) -> _Head:
    semi = np.array([rng.uniform(68.0, 74.0), rng.uniform(86.0, 94.0), rng.uniform(62.0, 69.0)])
    a_ref = semi.min()
    wob_h = _random_wobble(rng, _HEAD_WOBBLE_MM / a_ref)
    wob_b = _random_wobble(rng, _BRAIN_WOBBLE_MM / a_ref)
    t_scalp = rng.uniform(4.0, 5.0)
    t_skull = rng.uniform(5.5, 6.2)
    # two lateral ventricles: elongated antero-posteriorly, either side of the midline
    vy = rng.uniform(-6.0, 4.0)
    vz = rng.uniform(4.0, 12.0)
    ventricles = np.array(
        [
            [
                side * rng.uniform(7.0, 9.0),
                vy + rng.uniform(-2.0, 2.0),
                vz,
                rng.uniform(4.0, 6.0),
                rng.uniform(18.0, 24.0),
                rng.uniform(8.0, 11.0),
            ]
            for side in (-1.0, 1.0)
        ]
    )
    return _Head(semi, t_scalp, t_skull, wob_h, wob_b, ventricles)


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


def _check_positive(name: str, value: Any, *, allow_zero: bool = False) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a number, got {value!r}") from None
    if not np.isfinite(v) or v < 0 or (v == 0 and not allow_zero):
        raise InputError(
            f"{name} must be a finite number {'>=' if allow_zero else '>'} 0, got {value!r}"
        )
    return v


def _check_int(name: str, value: Any, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < minimum:
        raise InputError(f"{name} must be an integer >= {minimum}, got {value!r}")
    return int(value)


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
        spacing = _check_positive("pixel_spacing_mm", pixel_spacing_mm)
    if matrix_size is None and pixel_spacing_mm is None:
        matrix, spacing = preset_matrix, preset_spacing
    elif matrix_size is None:
        matrix = tuple(int(m) for m in np.ceil(fov / spacing - 1e-9))
    elif pixel_spacing_mm is None:
        spacing = float(np.max(fov / np.array(matrix)))
    thickness = _check_positive("slice_thickness_mm", slice_thickness_mm)
    gap = _check_positive("slice_gap_mm", slice_gap_mm, allow_zero=True)
    step = thickness + gap
    noise_fraction = _check_positive("noise_fraction", noise_fraction, allow_zero=True)
    if noise_fraction >= 1.0:
        raise InputError(f"noise_fraction must be < 1, got {noise_fraction!r}")
    bias_field_strength = _check_positive(
        "bias_field_strength", bias_field_strength, allow_zero=True
    )
    if bias_field_strength > 0.9:
        raise InputError(f"bias_field_strength must be <= 0.9, got {bias_field_strength!r}")
    fine_step_mm = _check_positive("fine_step_mm", fine_step_mm)
    n_sub_xy = _check_int("inplane_subsamples", inplane_subsamples, 1)
    n_sub_z = _check_int("slab_subsamples", slab_subsamples, 1)
    if n_slices is not None:
        n_slices = _check_int("n_slices", n_slices, 1)

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
