"""Mesh simplification to a face budget (spec section 6, Algorithm 2's target).

:func:`simplify_mesh` is the single entry point: it computes the target
``F_target = floor(F0 * (1 - P / 100))`` of Algorithm 2 and dispatches to one
method. Methods live in their own modules and take the mesh and an absolute
``target_faces``; to add one, write ``simplify_<name>(mesh, *, target_faces,
return_info=False, **options) -> Mesh | (Mesh, dict)`` and register it in
``_METHODS`` with its option names.

Methods
-------
``"curvature"``
    The paper's Algorithm 2: curvature-priority half-edge collapse with the
    volume-and-shape cost of Eq. 6, on the numba collapse engine
    (:func:`tumor3d.simplify.curvature.simplify_curvature`).
``"memoryless"``
    Lindstrom-Turk memoryless simplification (the paper's "MS" baseline) on
    the same engine (:func:`tumor3d.simplify.memoryless.simplify_memoryless`).
``"qem"``
    Quadric error metric edge collapse (QSlim baseline, ``fast-simplification``),
    :func:`tumor3d.simplify.qem.simplify_qem`.

Input requirements
------------------
``curvature`` and ``memoryless`` need a closed, consistently oriented
2-manifold (what :func:`tumor3d.geometry.surface.extract_surface` returns); any other
mesh is refused with an :class:`~tumor3d.errors.InputError` that counts its
boundary, non-manifold and inconsistent edges. Vertices where several closed
fans touch (pinches) are accepted and left untouched. ``qem`` accepts any
triangle mesh but may itself create non-manifold edges (see its module).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from fractions import Fraction
from typing import Any, Literal

import numpy as np

from tumor3d.errors import InputError
from tumor3d.geometry.mesh import Mesh
from tumor3d.geometry.surface import is_watertight, orient_outward
from tumor3d.simplify.curvature import simplify_curvature
from tumor3d.simplify.memoryless import simplify_memoryless
from tumor3d.simplify.qem import simplify_qem

__all__ = [
    "METHODS",
    "simplify_curvature",
    "simplify_memoryless",
    "simplify_mesh",
    "simplify_qem",
    "target_face_count",
]

#: method name -> (function(mesh, *, target_faces, return_info, **options), allowed option names)
_METHODS: dict[str, tuple[Callable[..., Any], frozenset[str]]] = {
    "curvature": (simplify_curvature, frozenset({"curvedness", "tau"})),
    "memoryless": (simplify_memoryless, frozenset()),
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
    method: Literal["curvature", "memoryless", "qem"] = "memoryless",
    reduction_percent: float,
    curvedness: Literal["sqrt", "no_root"] = "sqrt",
    ring_update: Literal["lazy", "eager"] = "lazy",
    return_info: bool = False,
    **options: Any,
) -> Mesh | tuple[Mesh, dict[str, Any]]:
    """Reduce a mesh's face count by ``reduction_percent`` percent.

    Parameters
    ----------
    mesh : Mesh
        A surface, normally closed and outward-oriented (from
        :func:`tumor3d.geometry.surface.extract_surface`). It is not modified.
    method : {"curvature", "memoryless", "qem"}, optional
        Simplification method (see the module docstring). The default,
        ``memoryless``, preserves the enclosed volume exactly and never
        breaks the manifold; ``curvature`` is the paper's Algorithm 2
        (``configs/paper.yaml``).
    reduction_percent : float
        ``P`` in [0, 100): the target is ``floor(F0 * (1 - P / 100))``
        faces (:func:`target_face_count`). ``P = 0`` returns ``mesh``
        itself, unchanged.
    curvedness : {"sqrt", "no_root"}, optional
        The ``curvature`` method's reading of Eq. 2 ([A17]); ignored by the
        other methods.
    ring_update : {"lazy", "eager"}, optional
        The ``curvature`` method's step 6 for a neighbour already in the
        candidate set: recomputed when it reaches the heap's top (``"lazy"``)
        or at once (``"eager"``, the paper's order); ignored by the others.
    return_info : bool, optional
        Also return diagnostics.
    **options
        Method-specific tuning (``qem``: ``aggressiveness``; ``curvature``:
        ``tau``, ``"once"`` as in the paper or ``"refresh"`` to reach the
        target, :func:`~tumor3d.simplify.curvature.simplify_curvature`).

    Returns
    -------
    mesh : Mesh
        The simplified mesh, faces oriented outward. A mesh whose
        ``F_target`` is below 4 faces (the smallest closed surface, a
        tetrahedron), including an empty mesh, is returned unchanged.
    info : dict, optional
        With ``return_info``: ``method``, ``reduction_percent``,
        ``n_faces_in`` (F0), ``target_faces`` (F_target), ``n_faces_out``,
        ``faces_over_target`` (``n_faces_out - target_faces``; negative when
        it undershoots), ``reduction_reached_percent``
        (``100 (1 - n_faces_out / F0)``), ``simplified`` (False for a
        pass-through), ``reason`` (why not, else None), ``watertight`` (of
        the result), plus the method's own diagnostics (``curvature`` and
        ``memoryless``: ``n_collapses``, ``candidates_exhausted``, ...;
        ``curvature``: ``stop_reason``, why it stopped above the target).

    Raises
    ------
    InputError
        On an unknown method or option, a ``P`` outside [0, 100), or (for
        ``curvature`` and ``memoryless``) a mesh that is not a closed,
        consistently oriented 2-manifold.
    """
    if not isinstance(mesh, Mesh):
        raise InputError(f"mesh must be a tumor3d.geometry.mesh.Mesh, got {type(mesh).__name__}")
    if method not in _METHODS:
        raise InputError(f"unknown simplification method {method!r}; choose one of {METHODS}")
    func, allowed = _METHODS[method]
    unknown = sorted(set(options) - allowed)
    if unknown:
        raise InputError(
            f"unknown option(s) {unknown} for simplification method {method!r}; "
            f"allowed: {sorted(allowed)}"
        )
    if method == "curvature":
        options = {**options, "curvedness": curvedness, "ring_update": ring_update}
    elif curvedness not in ("sqrt", "no_root"):
        raise InputError(f"curvedness must be 'sqrt' or 'no_root', got {curvedness!r}")
    elif ring_update not in ("lazy", "eager"):
        raise InputError(f"ring_update must be 'lazy' or 'eager', got {ring_update!r}")
    p = _check_percent(reduction_percent)
    n_in = mesh.n_faces
    target = target_face_count(n_in, p)
    reason = None
    method_info: dict[str, Any] = {}
    if p == 0.0:
        out = mesh
        reason = "reduction_percent is 0"
    elif mesh.is_empty:
        out = mesh
        reason = "the mesh is empty (no surface)"
    elif target < _MIN_FACES:
        out = mesh
        reason = (
            f"F_target={target} of F0={n_in} faces is below {_MIN_FACES} "
            "(the smallest closed surface); returned unchanged"
        )
    else:
        out, method_info = func(mesh, target_faces=target, return_info=True, **options)
        out = orient_outward(out)
    if not return_info:
        return out
    info = {
        "method": method,
        "reduction_percent": p,
        "n_faces_in": n_in,
        "target_faces": target,
        "n_faces_out": out.n_faces,
        "faces_over_target": out.n_faces - target,
        "reduction_reached_percent": 100.0 * (1.0 - out.n_faces / n_in) if n_in else 0.0,
        "simplified": reason is None,
        "reason": reason,
        "watertight": bool(not out.is_empty and is_watertight(out)),
        **method_info,
    }
    return out, info
