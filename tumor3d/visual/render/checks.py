"""Checks of the parameters of :mod:`tumor3d.visual.render` (:class:`InputError` naming them)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from tumor3d.errors import InputError
from tumor3d.geometry.mesh import Mesh


def _check_color(value: Sequence[float], name: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name} must be 3 numbers in [0, 1], got {value!r}") from None
    if arr.shape != (3,) or not np.all(np.isfinite(arr)) or arr.min() < 0 or arr.max() > 1:
        raise InputError(f"{name} must be 3 numbers in [0, 1], got {value!r}")
    return arr


def _check_number(value: float, name: str, lo: float, hi: float, *, closed: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise InputError(f"{name} must be a number, got {value!r}")
    v = float(value)
    ok = (lo <= v <= hi) if closed else (lo < v < hi)
    if not (math.isfinite(v) and ok):
        kind = "in" if closed else "strictly between"
        raise InputError(f"{name} must lie {kind} {lo} and {hi}, got {value}")
    return v


def _check_int(value: int, name: str, lo: int, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise InputError(f"{name} must be an integer, got {value!r}")
    if not lo <= value <= hi:
        raise InputError(f"{name} must lie in [{lo}, {hi}], got {value}")
    return int(value)


def _check_names(value: Sequence[str], name: str, allowed: Sequence[str]) -> tuple[str, ...]:
    if isinstance(value, str) or not isinstance(value, Sequence):
        raise InputError(f"{name} must be a sequence of names from {list(allowed)}, got {value!r}")
    names = tuple(value)
    bad = [x for x in names if x not in allowed]
    if bad:
        raise InputError(f"{name}: unknown name(s) {bad}; choose from {list(allowed)}")
    if len(set(names)) != len(names):
        raise InputError(f"{name} lists a name twice: {list(names)}")
    return names


def _check_mesh(mesh: Any, name: str) -> Mesh:
    if not isinstance(mesh, Mesh):
        raise InputError(f"{name} must be a tumor3d.geometry.mesh.Mesh, got {type(mesh).__name__}")
    if mesh.is_empty:
        raise InputError(f"cannot render an empty {name} mesh (it has no faces)")
    return mesh
