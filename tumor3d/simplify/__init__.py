"""Mesh simplification to a face budget (spec section 6, Algorithm 2's target).

:func:`simplify_mesh` is the single entry point: it computes the target
``F_target = floor(F0 * (1 - P / 100))`` of Algorithm 2 and dispatches to one
method. Methods live in their own modules and take the mesh and an absolute
``target_faces``; to add one, write ``simplify_<name>(mesh, *, target_faces,
**options) -> Mesh`` and register it in ``_METHODS`` with its option names.

Methods
-------
``"qem"``
    Quadric error metric edge collapse (QSlim baseline),
    :func:`tumor3d.simplify.qem.simplify_qem`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from fractions import Fraction
from typing import Any, Literal

import numpy as np

from tumor3d.errors import InputError
from tumor3d.mesh import Mesh
from tumor3d.simplify.qem import simplify_qem
from tumor3d.surface import is_watertight

__all__ = ["METHODS", "simplify_mesh", "simplify_qem", "target_face_count"]

#: method name -> (function(mesh, *, target_faces, **options) -> Mesh, allowed option names)
_METHODS: dict[str, tuple[Callable[..., Mesh], frozenset[str]]] = {
    "qem": (simplify_qem, frozenset({"aggressiveness"})),
}
METHODS: tuple[str, ...] = tuple(_METHODS)

_MIN_FACES = 4  # the smallest closed triangle surface (a tetrahedron)


def _check_percent(reduction_percent: float) -> float:
    if isinstance(reduction_percent, bool) or not isinstance(
        reduction_percent, (int, float, np.integer, np.floating)
    ):
        raise InputError(f"reduction_percent must be a number, got {reduction_percent!r}")
    p = float(reduction_percent)
    if not (math.isfinite(p) and 0.0 <= p < 100.0):
        raise InputError(f"reduction_percent must lie in [0, 100), got {reduction_percent}")
    return p


def target_face_count(n_faces: int, reduction_percent: float) -> int:
    """Face budget of Algorithm 2: ``F_target = floor(F0 * (1 - P / 100))``.

    Computed in exact decimal arithmetic on ``repr(P)``, so that e.g.
    ``F0 = 6116`` gives 3669, 2446 and 1223 at ``P = 40, 60, 80`` as in the
    paper's Fig. 9, with no floating-point rounding below an exact integer.

    Parameters
    ----------
    n_faces : int
        ``F0``, at least 0.
    reduction_percent : float
        ``P`` in [0, 100).

    Returns
    -------
    int

    Examples
    --------
    >>> [target_face_count(6116, p) for p in (0, 40, 60, 80)]
    [6116, 3669, 2446, 1223]
    """
    if isinstance(n_faces, bool) or not isinstance(n_faces, (int, np.integer)) or n_faces < 0:
        raise InputError(f"n_faces must be a non-negative integer, got {n_faces!r}")
    p = _check_percent(reduction_percent)
    exact = Fraction(int(n_faces)) * (100 - Fraction(repr(p))) / 100
    return int(math.floor(exact))


def simplify_mesh(
    mesh: Mesh,
    *,
    method: Literal["qem"] = "qem",
    reduction_percent: float,
    return_info: bool = False,
    **options: Any,
) -> Mesh | tuple[Mesh, dict[str, Any]]:
    """Reduce a mesh's face count by ``reduction_percent`` percent.

    Parameters
    ----------
    mesh : Mesh
        A non-empty surface, normally closed and outward-oriented (from
        :func:`tumor3d.surface.extract_surface`). It is not modified.
    method : {"qem"}
        Simplification method (see the module docstring).
    reduction_percent : float
        ``P`` in [0, 100): the target is ``floor(F0 * (1 - P / 100))``
        faces (:func:`target_face_count`). ``P = 0`` returns ``mesh``
        itself, unchanged.
    return_info : bool, optional
        Also return diagnostics.
    **options
        Method-specific tuning (``qem``: ``aggressiveness``).

    Returns
    -------
    mesh : Mesh
        The simplified mesh, faces oriented outward.
    info : dict, optional
        With ``return_info``: ``method``, ``reduction_percent``,
        ``n_faces_in`` (F0), ``target_faces`` (F_target), ``n_faces_out``,
        ``faces_over_target`` (``n_faces_out - target_faces``; negative when
        it undershoots), ``watertight`` (of the result).

    Raises
    ------
    InputError
        On an unknown method or option, a ``P`` outside [0, 100), an empty
        mesh, or a ``P`` that leaves fewer than 4 faces.
    """
    if not isinstance(mesh, Mesh):
        raise InputError(f"mesh must be a tumor3d.mesh.Mesh, got {type(mesh).__name__}")
    if method not in _METHODS:
        raise InputError(f"unknown simplification method {method!r}; choose one of {METHODS}")
    func, allowed = _METHODS[method]
    unknown = sorted(set(options) - allowed)
    if unknown:
        raise InputError(
            f"unknown option(s) {unknown} for simplification method {method!r}; "
            f"allowed: {sorted(allowed)}"
        )
    p = _check_percent(reduction_percent)
    if mesh.is_empty:
        raise InputError("cannot simplify an empty mesh (it has no faces)")
    n_in = mesh.n_faces
    target = target_face_count(n_in, p)
    if p == 0.0:
        out = mesh
    else:
        if target < _MIN_FACES:
            raise InputError(
                f"reduction_percent={reduction_percent} leaves F_target={target} of "
                f"F0={n_in} faces; a closed surface needs at least {_MIN_FACES}"
            )
        out = func(mesh, target_faces=target, **options)
    if not return_info:
        return out
    info = {
        "method": method,
        "reduction_percent": p,
        "n_faces_in": n_in,
        "target_faces": target,
        "n_faces_out": out.n_faces,
        "faces_over_target": out.n_faces - target,
        "watertight": is_watertight(out),
    }
    return out, info
