r"""Lindstrom-Turk memoryless simplification (the paper's "MS" baseline, spec section 9).

Greedy edge collapse on :mod:`tumor3d.simplify._engine`, by increasing cost,
each edge moved to its optimal point. Cost and placement are computed from
the *current* mesh only (no per-vertex quadric memory of the original), as in
Lindstrom & Turk (1998):

* over the faces ``T`` around the edge, with ``n_t = (b - a) x (c - a)`` and
  ``d_t = a . (b x c)``, the signed volume of the tetrahedron swept by face
  ``t`` when the edge moves to ``p`` is ``V_t(p) = (d_t - n_t . p) / 6``;
* placement: the point satisfying, in order and each only if
  alpha-compatible (alpha = 1 degree) with the constraints already taken,
  *volume preservation* ``sum_t V_t(p) = 0``, *volume optimisation*
  ``min sum_t V_t(p)^2``, *boundary preservation/optimisation* (no terms:
  the meshes here are closed) and *triangle-shape optimisation*
  ``min sum_k ||p - v_k||^2`` over the link vertices;
* cost: ``sum_t V_t(p)^2`` (mm^6), the volume objective at ``p``.

The total enclosed volume is preserved exactly by each collapse (up to
rounding) whenever the volume-preservation constraint is taken; the
validity checks of the engine ([A21]) keep the surface closed, manifold and
oriented.

No maintained Python package offers this method (CGAL's
``Surface_mesh_simplification`` with ``LindstromTurk_cost/placement`` is the
C++ reference).

References
----------
P. Lindstrom, G. Turk, "Fast and memory efficient polygonal simplification",
IEEE Visualization 1998, 279-286, doi:10.1109/VISUAL.1998.745314.
P. Lindstrom, G. Turk, "Evaluation of memoryless simplification", IEEE TVCG
5(2), 1999, 98-115, doi:10.1109/2945.773803.
"""

from __future__ import annotations

from typing import Any

from tumor3d.geometry.mesh import Mesh
from tumor3d.simplify import _engine
from tumor3d.simplify._prepare import DEFAULT_TOLERANCES, check_target, prepare

__all__ = ["simplify_memoryless"]


def simplify_memoryless(
    mesh: Mesh, *, target_faces: int, return_info: bool = False
) -> Mesh | tuple[Mesh, dict[str, Any]]:
    """Simplify a closed mesh to ``target_faces`` faces by Lindstrom-Turk edge collapse.

    Parameters
    ----------
    mesh : Mesh
        A closed, consistently oriented 2-manifold (not modified).
    target_faces : int
        ``1 <= target_faces <= mesh.n_faces``.
    return_info : bool, optional
        Also return diagnostics.

    Returns
    -------
    mesh : Mesh
        The simplified mesh, closed and oriented like the input.
    info : dict, optional
        ``n_faces_reached``, ``n_collapses``, ``n_pops``,
        ``candidates_exhausted`` (no valid edge was left above the target),
        ``n_pinched_vertices``.

    Raises
    ------
    InputError
        On a bad target or a mesh that is not a closed oriented 2-manifold.
    """
    target = check_target(mesh, target_faces)
    arr = prepare(mesh, "memoryless")
    tol = DEFAULT_TOLERANCES
    v = arr.vertices
    f = arr.faces
    face_alive, _, n_faces, n_coll, n_pops = _engine.run_edge_priority(
        v, f, arr.head, arr.nxt, arr.status, target, _engine.POLICY_MEMORYLESS,
        tol.max_star, tol.min_quality,
    )  # fmt: skip
    out_v, out_f = _engine.compact(v, f, face_alive)
    out = Mesh(out_v, out_f)
    if not return_info:
        return out
    info = {
        "n_faces_reached": int(n_faces),
        "n_collapses": int(n_coll),
        "n_pops": int(n_pops),
        "candidates_exhausted": bool(n_faces > target),
        "n_pinched_vertices": arr.n_pinched,
    }
    return out, info
