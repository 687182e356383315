"""The synthetic head model: layered wobbly ellipsoids and two ventricles."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from tumor3d.phantom.raster import _MONOMIALS, _WOBBLE_BALL

# Nominal layer thicknesses (mm) and shape ranges.
_HEAD_WOBBLE_MM = 5.0
_BRAIN_WOBBLE_MM = 0.8
_T_CSF_MM = 2.0
_T_GM_MM = 3.0


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
        hw_h = _wobble_hessian(self.wob_h)
        amin = self.semi_axes.min()
        return np.concatenate(
            [
                self.center,
                self.semi_axes,
                self.thresholds(),
                [(1.0 + lw_h) / amin, (1.0 + lw_h + lw_b) / amin],
                [hw_h, hw_h + _wobble_hessian(self.wob_b)],
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


def _wobble_hessian(coef: np.ndarray) -> float:
    """Rigorous bound of the Hessian's norm of ``w`` in ``q`` on the ball ``|q| <= 1.2``.

    A monomial of degree ``n`` has second derivatives ``a_i (a_j - [i = j]) q^(a - e_i - e_j)``,
    whose absolute values sum to at most ``n (n - 1) |q|^(n - 2)``, which bounds the norm.
    """
    deg = _MONOMIALS.sum(axis=1)
    return float(np.sum(np.abs(coef) * deg * (deg - 1) * _WOBBLE_BALL ** np.maximum(deg - 2, 0)))


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
