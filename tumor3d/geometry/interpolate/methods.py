"""The methods and parts modes of :mod:`tumor3d.geometry.interpolate`; checks of the parameters."""

from __future__ import annotations

import math
from typing import Literal

from tumor3d.errors import InputError
from tumor3d.geometry.distance import (
    check_spacing,
)

Method = Literal["enhanced", "enhanced-edt", "shape", "shape-edt", "linear"]


Parts = Literal["whole", "matched"]


#: method -> (distance metric, align on centroids); "linear" uses no distance.
_METHOD_SPEC: dict[str, tuple[str, bool]] = {
    "enhanced": ("chamfer", True),
    "enhanced-edt": ("euclidean", True),
    "shape": ("taxicab", False),
    "shape-edt": ("euclidean", False),
    "linear": ("chamfer", False),
}


METHODS: tuple[str, ...] = tuple(_METHOD_SPEC)


_PARTS = ("whole", "matched")


_DEFAULT_METHOD = "shape-edt"


_DEFAULT_PARTS = "matched"


def _check_method(method: object) -> str:
    if method not in _METHOD_SPEC:
        raise InputError(f"method must be one of {METHODS}, got {method!r}")
    return str(method)


def _check_parts(parts: object) -> str:
    if parts not in _PARTS:
        raise InputError(f"parts must be one of {_PARTS}, got {parts!r}")
    return str(parts)


def _check_t(t: object) -> float:
    try:
        value = float(t)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(f"t must be a number in the open interval (0, 1), got {t!r}") from None
    if not (0.0 < value < 1.0):
        raise InputError(f"t must lie in the open interval (0, 1), got {t!r}")
    return value


def _check_positive(value: object, name: str) -> float:
    try:
        out = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(f"{name} must be a positive number of mm, got {value!r}") from None
    if not (math.isfinite(out) and out > 0.0):
        raise InputError(f"{name} must be a positive finite number of mm, got {value!r}")
    return out


def _spacing_or_unit(pixel_spacing_mm: object) -> tuple[float, float]:
    if pixel_spacing_mm is None:
        return (1.0, 1.0)
    return check_spacing(pixel_spacing_mm, "pixel_spacing_mm")
