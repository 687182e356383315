"""Validity checks of an edge collapse and the collapse itself (numba kernels).

See :mod:`tumor3d.simplify._engine` for the rules ([A21]): link condition,
no tetrahedron, no flipped, degenerate or needle face, bounded star.
"""

from __future__ import annotations

import math

import numba

from tumor3d.simplify._jit import _FASTMATH
from tumor3d.simplify._topology import _gather_star, _slot

_SQRT3x4 = 4.0 * math.sqrt(3.0)


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _tri_normal(p0x, p0y, p0z, p1x, p1y, p1z, p2x, p2y, p2z):  # pragma: no cover
    ax = p1x - p0x
    ay = p1y - p0y
    az = p1z - p0z
    bx = p2x - p0x
    by = p2y - p0y
    bz = p2z - p0z
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _sum_sq_edges(p0x, p0y, p0z, p1x, p1y, p1z, p2x, p2y, p2z):  # pragma: no cover
    return (
        (p1x - p0x) ** 2
        + (p1y - p0y) ** 2
        + (p1z - p0z) ** 2
        + (p2x - p1x) ** 2
        + (p2y - p1y) ** 2
        + (p2z - p1z) ** 2
        + (p0x - p2x) ** 2
        + (p0y - p2y) ** 2
        + (p0z - p2z) ** 2
    )


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _check_star_geometry(
    i, j, px, py, pz, V, F, star, n, want_cost, min_quality
):  # pragma: no cover - numba
    """Check the faces of ``star`` (around ``i``) not containing ``j`` when ``i`` moves to p.

    Returns ``(ok, sum V(t)(1 - S(t')), sum (1 - S(t')))`` where
    ``V(t) = |det[a - v_i, b - v_i, p - v_i]| / 6`` (Eq. 4, [A19]) and
    ``S`` is Eq. 5 on the post-collapse triangle ([A20]).
    """
    cost = 0.0
    sq = 0.0
    vix = V[i, 0]
    viy = V[i, 1]
    viz = V[i, 2]
    for k in range(n):
        f = star[k]
        r = _slot(F, f, i)
        if F[f, 0] == j or F[f, 1] == j or F[f, 2] == j:
            continue
        a = F[f, (r + 1) % 3]
        b = F[f, (r + 2) % 3]
        ax = V[a, 0]
        ay = V[a, 1]
        az = V[a, 2]
        bx = V[b, 0]
        by = V[b, 1]
        bz = V[b, 2]
        n0x, n0y, n0z = _tri_normal(vix, viy, viz, ax, ay, az, bx, by, bz)
        n1x, n1y, n1z = _tri_normal(px, py, pz, ax, ay, az, bx, by, bz)
        if n0x * n1x + n0y * n1y + n0z * n1z <= 0.0:
            return False, 0.0, 0.0
        l2 = _sum_sq_edges(px, py, pz, ax, ay, az, bx, by, bz)
        norm1 = math.sqrt(n1x * n1x + n1y * n1y + n1z * n1z)
        if not norm1 > 1e-12 * l2:
            return False, 0.0, 0.0
        s_new = _SQRT3x4 * 0.5 * norm1 / l2
        if s_new < min_quality:
            l2o = _sum_sq_edges(vix, viy, viz, ax, ay, az, bx, by, bz)
            norm0 = math.sqrt(n0x * n0x + n0y * n0y + n0z * n0z)
            s_old = _SQRT3x4 * 0.5 * norm0 / l2o if l2o > 0.0 else 0.0
            if s_new < s_old:
                return False, 0.0, 0.0
        if want_cost:
            # det[a - vi, b - vi, p - vi] = (p - vi) . ((a - vi) x (b - vi)) = (p - vi) . n0
            vol = abs((px - vix) * n0x + (py - viy) * n0y + (pz - viz) * n0z) / 6.0
            cost += vol * (1.0 - s_new)
            sq += 1.0 - s_new
    return True, cost, sq


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _star_table(i, V, F, star, n, gab, gs):  # pragma: no cover - numba
    """Opposite vertices ``(a, b)``, their positions and ``n(t)`` of each face around ``v_i``.

    The per-face quantities of :func:`_check_star_geometry` that do not depend on
    ``v_j`` (the same operations, so the same bits), computed once per popped vertex.
    """
    vix = V[i, 0]
    viy = V[i, 1]
    viz = V[i, 2]
    for k in range(n):
        f = star[k]
        r = _slot(F, f, i)
        a = F[f, (r + 1) % 3]
        b = F[f, (r + 2) % 3]
        gab[k, 0] = a
        gab[k, 1] = b
        ax = V[a, 0]
        ay = V[a, 1]
        az = V[a, 2]
        bx = V[b, 0]
        by = V[b, 1]
        bz = V[b, 2]
        gs[k, 0] = ax
        gs[k, 1] = ay
        gs[k, 2] = az
        gs[k, 3] = bx
        gs[k, 4] = by
        gs[k, 5] = bz
        n0x, n0y, n0z = _tri_normal(vix, viy, viz, ax, ay, az, bx, by, bz)
        gs[k, 6] = n0x
        gs[k, 7] = n0y
        gs[k, 8] = n0z


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _star_geometry_table(
    j, vix, viy, viz, px, py, pz, gab, gs, n, min_quality
):  # pragma: no cover - numba
    """:func:`_check_star_geometry` (``want_cost``) on the table of :func:`_star_table`."""
    cost = 0.0
    sq = 0.0
    for k in range(n):
        if gab[k, 0] == j or gab[k, 1] == j:
            continue
        ax = gs[k, 0]
        ay = gs[k, 1]
        az = gs[k, 2]
        bx = gs[k, 3]
        by = gs[k, 4]
        bz = gs[k, 5]
        n0x = gs[k, 6]
        n0y = gs[k, 7]
        n0z = gs[k, 8]
        n1x, n1y, n1z = _tri_normal(px, py, pz, ax, ay, az, bx, by, bz)
        if n0x * n1x + n0y * n1y + n0z * n1z <= 0.0:
            return False, 0.0, 0.0
        l2 = _sum_sq_edges(px, py, pz, ax, ay, az, bx, by, bz)
        norm1 = math.sqrt(n1x * n1x + n1y * n1y + n1z * n1z)
        if not norm1 > 1e-12 * l2:
            return False, 0.0, 0.0
        s_new = _SQRT3x4 * 0.5 * norm1 / l2
        if s_new < min_quality:
            l2o = _sum_sq_edges(vix, viy, viz, ax, ay, az, bx, by, bz)
            norm0 = math.sqrt(n0x * n0x + n0y * n0y + n0z * n0z)
            s_old = _SQRT3x4 * 0.5 * norm0 / l2o if l2o > 0.0 else 0.0
            if s_new < s_old:
                return False, 0.0, 0.0
        vol = abs((px - vix) * n0x + (py - viy) * n0y + (pz - viz) * n0z) / 6.0
        cost += vol * (1.0 - s_new)
        sq += 1.0 - s_new
    return True, cost, sq


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _prepare_i(i, F, face_alive, head, nxt, mark, stamp, si):  # pragma: no cover - numba
    """Gather the star of ``v_i`` into ``si`` and stamp its neighbours; return ``(n_i, stamp)``."""
    ni = _gather_star(i, F, face_alive, head, nxt, si)
    stamp[0] += 1
    s1 = stamp[0]
    if ni <= si.shape[0]:
        for k in range(ni):
            f = si[k]
            r = _slot(F, f, i)
            mark[F[f, (r + 1) % 3]] = s1
    return ni, s1


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _check_topology_j(
    i, ni, si, s1, j, F, face_alive, locked, head, nxt, mark, sj, max_star
):  # pragma: no cover - numba
    """Topological part of :func:`_check_collapse_j`; returns ``n_j`` (or -1 when invalid).

    The star of ``v_j`` is left in ``sj[:n_j]``.
    """
    if i == j or locked[i] or locked[j] or ni > si.shape[0]:
        return -1
    nj = _gather_star(j, F, face_alive, head, nxt, sj)
    if nj > sj.shape[0] or ni + nj - 4 > max_star:
        return -1
    # faces of the edge and their opposite vertices
    ne = 0
    a = -1
    b = -1
    for k in range(ni):
        f = si[k]
        if F[f, 0] == j or F[f, 1] == j or F[f, 2] == j:
            ne += 1
            o = F[f, 0] + F[f, 1] + F[f, 2] - i - j
            if a == -1:
                a = o
            else:
                b = o
    if ne != 2 or a == b:
        return -1
    # link condition: the common neighbours are exactly {a, b} (fan neighbours are distinct)
    common = 0
    for k in range(nj):
        f = sj[k]
        r = _slot(F, f, j)
        if mark[F[f, (r + 1) % 3]] == s1:
            common += 1
    if common != 2:
        return -1
    # tetrahedron: faces (i, a, b) and (j, a, b) both present
    abi = False
    for k in range(ni):
        f = si[k]
        if _slot(F, f, a) >= 0 and _slot(F, f, b) >= 0:
            abi = True
    if abi:
        for k in range(nj):
            f = sj[k]
            if _slot(F, f, a) >= 0 and _slot(F, f, b) >= 0:
                return -1
    return nj


@numba.njit(cache=True, fastmath=_FASTMATH)
def _check_collapse_j(
    i, ni, si, s1, j, px, py, pz, move_j, V, F, face_alive, locked, head, nxt, mark, sj,
    max_star, min_quality,
):  # pragma: no cover - numba
    r"""Whether ``v_i -> v_j`` (``v_j`` moved to p) keeps the mesh a valid closed manifold.

    ``si[:ni]`` is the star of ``v_i`` and its neighbours carry the stamp
    ``s1`` (:func:`_prepare_i`). Returns ``(ok, cost, sum_q)``: the Eq. 6
    cost and ``sum (1 - S(t'))`` over ``T_{v_i} \ T_{e}`` (the paper's cost
    for the half-edge collapse, where ``p = v_j``).
    """
    nj = _check_topology_j(i, ni, si, s1, j, F, face_alive, locked, head, nxt, mark, sj, max_star)
    if nj < 0:
        return False, 0.0, 0.0
    ok, cost, sq = _check_star_geometry(i, j, px, py, pz, V, F, si, ni, True, min_quality)
    if not ok:
        return False, 0.0, 0.0
    if move_j:
        ok2, _, _ = _check_star_geometry(j, i, px, py, pz, V, F, sj, nj, False, min_quality)
        if not ok2:
            return False, 0.0, 0.0
    return True, cost, sq


@numba.njit(cache=True, fastmath=_FASTMATH)
def _collapse(i, j, px, py, pz, V, F, face_alive, vertex_alive, head, nxt, buf):  # pragma: no cover
    """Collapse ``v_i -> v_j`` and put ``v_j`` at p; return the number of faces removed."""
    n = _gather_star(i, F, face_alive, head, nxt, buf)
    return _collapse_star(i, j, px, py, pz, V, F, face_alive, vertex_alive, head, nxt, buf, n)


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _collapse_star(
    i, j, px, py, pz, V, F, face_alive, vertex_alive, head, nxt, buf, n
):  # pragma: no cover - numba
    """:func:`_collapse` with the star of ``v_i`` already gathered in ``buf[:n]``."""
    removed = 0
    for k in range(n):
        f = buf[k]
        r = _slot(F, f, i)
        if F[f, 0] == j or F[f, 1] == j or F[f, 2] == j:
            face_alive[f] = False
            removed += 1
        else:
            F[f, r] = j
            c = 3 * f + r
            nxt[c] = head[j]
            head[j] = c
    head[i] = -1
    vertex_alive[i] = False
    V[j, 0] = px
    V[j, 1] = py
    V[j, 2] = pz
    return removed
