"""Cost and placement of an edge collapse for the edge scheduler (numba kernels).

``policy`` chooses them (``POLICY_MEMORYLESS`` = Lindstrom-Turk); a new
policy is one more branch in :func:`_edge_cost_place`.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from tumor3d.simplify._collapse import _tri_normal
from tumor3d.simplify._heap import _heap_push
from tumor3d.simplify._jit import _FASTMATH
from tumor3d.simplify._topology import _gather_star

POLICY_MEMORYLESS = 0  #: Lindstrom-Turk memoryless cost and placement
POLICY_MIDPOINT = 1  #: squared edge length, midpoint placement (engine tests)
_COS2_ALPHA = math.cos(math.radians(1.0)) ** 2  # Lindstrom-Turk alpha = 1 degree
_SIN2_ALPHA = math.sin(math.radians(1.0)) ** 2


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _add_constraint(A, b, n, ax, ay, az, rhs):  # pragma: no cover - numba
    """Lindstrom-Turk alpha-compatible constraint accumulation; returns the new count."""
    aa = ax * ax + ay * ay + az * az
    if not aa > 0.0 or n >= 3:
        return n
    if n == 1:
        d = A[0, 0] * ax + A[0, 1] * ay + A[0, 2] * az
        a0 = A[0, 0] ** 2 + A[0, 1] ** 2 + A[0, 2] ** 2
        if not d * d < a0 * aa * _COS2_ALPHA:
            return n
    elif n == 2:
        qx = A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]
        qy = A[0, 2] * A[1, 0] - A[0, 0] * A[1, 2]
        qz = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
        d = qx * ax + qy * ay + qz * az
        if not d * d > aa * (qx * qx + qy * qy + qz * qz) * _SIN2_ALPHA:
            return n
    A[n, 0] = ax
    A[n, 1] = ay
    A[n, 2] = az
    b[n] = rhs
    return n + 1


@numba.njit(cache=True, fastmath=_FASTMATH)
def _add_gradient(A, b, n, H, r):  # pragma: no cover - numba
    """Add the constraints of ``min 1/2 v^T H v - r^T v`` restricted to the current null space."""
    if n == 0:
        for k in range(3):
            n = _add_constraint(A, b, n, H[k, 0], H[k, 1], H[k, 2], r[k])
    elif n == 1:
        a0x = A[0, 0]
        a0y = A[0, 1]
        a0z = A[0, 2]
        # an axis least aligned with A0, then an orthonormal basis q0, q1 of A0's orthogonal plane
        ex = 0.0
        ey = 0.0
        ez = 0.0
        if abs(a0x) <= abs(a0y) and abs(a0x) <= abs(a0z):
            ex = 1.0
        elif abs(a0y) <= abs(a0z):
            ey = 1.0
        else:
            ez = 1.0
        q0x = a0y * ez - a0z * ey
        q0y = a0z * ex - a0x * ez
        q0z = a0x * ey - a0y * ex
        q1x = a0y * q0z - a0z * q0y
        q1y = a0z * q0x - a0x * q0z
        q1z = a0x * q0y - a0y * q0x
        for q in range(2):
            if q == 0:
                qx, qy, qz = q0x, q0y, q0z
            else:
                qx, qy, qz = q1x, q1y, q1z
            rx = H[0, 0] * qx + H[1, 0] * qy + H[2, 0] * qz
            ry = H[0, 1] * qx + H[1, 1] * qy + H[2, 1] * qz
            rz = H[0, 2] * qx + H[1, 2] * qy + H[2, 2] * qz
            n = _add_constraint(A, b, n, rx, ry, rz, qx * r[0] + qy * r[1] + qz * r[2])
    elif n == 2:
        qx = A[0, 1] * A[1, 2] - A[0, 2] * A[1, 1]
        qy = A[0, 2] * A[1, 0] - A[0, 0] * A[1, 2]
        qz = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
        rx = H[0, 0] * qx + H[1, 0] * qy + H[2, 0] * qz
        ry = H[0, 1] * qx + H[1, 1] * qy + H[2, 1] * qz
        rz = H[0, 2] * qx + H[1, 2] * qy + H[2, 2] * qz
        n = _add_constraint(A, b, n, rx, ry, rz, qx * r[0] + qy * r[1] + qz * r[2])
    return n


@numba.njit(cache=True, fastmath=_FASTMATH)
def _solve3(A, b):  # pragma: no cover - numba
    """Cramer's rule for a 3x3 system; ``ok`` False when singular."""
    det = (
        A[0, 0] * (A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1])
        - A[0, 1] * (A[1, 0] * A[2, 2] - A[1, 2] * A[2, 0])
        + A[0, 2] * (A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0])
    )
    if det == 0.0 or not math.isfinite(det):
        return False, 0.0, 0.0, 0.0
    x = (
        b[0] * (A[1, 1] * A[2, 2] - A[1, 2] * A[2, 1])
        - A[0, 1] * (b[1] * A[2, 2] - A[1, 2] * b[2])
        + A[0, 2] * (b[1] * A[2, 1] - A[1, 1] * b[2])
    ) / det
    y = (
        A[0, 0] * (b[1] * A[2, 2] - A[1, 2] * b[2])
        - b[0] * (A[1, 0] * A[2, 2] - A[1, 2] * A[2, 0])
        + A[0, 2] * (A[1, 0] * b[2] - b[1] * A[2, 0])
    ) / det
    z = (
        A[0, 0] * (A[1, 1] * b[2] - b[1] * A[2, 1])
        - A[0, 1] * (A[1, 0] * b[2] - b[1] * A[2, 0])
        + b[0] * (A[1, 0] * A[2, 1] - A[1, 1] * A[2, 0])
    ) / det
    return True, x, y, z


@numba.njit(cache=True, fastmath=_FASTMATH)
def _lt_cost_place(u, v, V, F, su, nu, sv, nv_, mark, stamp, cA, cb, H, r):  # pragma: no cover
    """Lindstrom-Turk memoryless placement and cost of collapsing edge (u, v).

    Over the faces ``T`` around u or v, with ``n_t = (b - a) x (c - a)`` and
    ``d_t = a . (b x c)`` for ``t = (a, b, c)``, the signed volume swept when
    the edge moves to ``p`` is ``V_t(p) = (d_t - n_t . p) / 6``. Constraints,
    in order, each kept only if alpha-compatible (alpha = 1 degree) with
    those before: volume preservation ``sum_t V_t(p) = 0``; volume
    optimisation ``min sum_t V_t(p)^2``; (boundary terms vanish on a closed
    mesh); triangle-shape optimisation ``min sum_k ||p - v_k||^2`` over the
    link vertices. Cost ``sum_t V_t(p)^2 = (sum d_t^2 - 2 p . sum d_t n_t +
    p^T (sum n_t n_t^T) p) / 36`` (the volume objective), evaluated in
    coordinates centred on u to avoid cancellation.
    """
    ox = V[u, 0]
    oy = V[u, 1]
    oz = V[u, 2]
    h00 = 0.0
    h01 = 0.0
    h02 = 0.0
    h11 = 0.0
    h12 = 0.0
    h22 = 0.0
    r0 = 0.0
    r1 = 0.0
    r2 = 0.0
    sx = 0.0
    sy = 0.0
    sz = 0.0
    sd = 0.0
    sdd = 0.0
    stamp[0] += 1
    s = stamp[0]
    mark[u] = s
    mark[v] = s
    nlink = 0
    lx = 0.0
    ly = 0.0
    lz = 0.0
    for k in range(nu + nv_):
        if k < nu:
            f = su[k]
        else:
            f = sv[k - nu]
            if F[f, 0] == u or F[f, 1] == u or F[f, 2] == u:
                continue  # an edge face, already counted from u's side
        a = F[f, 0]
        b = F[f, 1]
        c = F[f, 2]
        ax = V[a, 0] - ox
        ay = V[a, 1] - oy
        az = V[a, 2] - oz
        bx = V[b, 0] - ox
        by = V[b, 1] - oy
        bz = V[b, 2] - oz
        cx = V[c, 0] - ox
        cy = V[c, 1] - oy
        cz = V[c, 2] - oz
        nx, ny, nz = _tri_normal(ax, ay, az, bx, by, bz, cx, cy, cz)
        d = ax * (by * cz - bz * cy) + ay * (bz * cx - bx * cz) + az * (bx * cy - by * cx)
        sx += nx
        sy += ny
        sz += nz
        sd += d
        sdd += d * d
        h00 += nx * nx
        h01 += nx * ny
        h02 += nx * nz
        h11 += ny * ny
        h12 += ny * nz
        h22 += nz * nz
        r0 += d * nx
        r1 += d * ny
        r2 += d * nz
        for t in range(3):
            w = F[f, t]
            if mark[w] != s:
                mark[w] = s
                nlink += 1
                lx += V[w, 0] - ox
                ly += V[w, 1] - oy
                lz += V[w, 2] - oz
    H[0, 0] = h00
    H[0, 1] = h01
    H[0, 2] = h02
    H[1, 0] = h01
    H[1, 1] = h11
    H[1, 2] = h12
    H[2, 0] = h02
    H[2, 1] = h12
    H[2, 2] = h22
    r[0] = r0
    r[1] = r1
    r[2] = r2
    n = _add_constraint(cA, cb, 0, sx, sy, sz, sd)
    n = _add_gradient(cA, cb, n, H, r)
    if n < 3 and nlink > 0:
        for a in range(3):
            for c in range(3):
                H[a, c] = 0.0
            H[a, a] = float(nlink)
        r[0] = lx
        r[1] = ly
        r[2] = lz
        n = _add_gradient(cA, cb, n, H, r)
    if n < 3:
        return False, np.inf, 0.0, 0.0, 0.0
    ok, px, py, pz = _solve3(cA, cb)
    if not ok:
        return False, np.inf, 0.0, 0.0, 0.0
    quad = (
        h00 * px * px + h11 * py * py + h22 * pz * pz
        + 2.0 * (h01 * px * py + h02 * px * pz + h12 * py * pz)
    )  # fmt: skip
    cost = max(0.0, sdd - 2.0 * (r0 * px + r1 * py + r2 * pz) + quad) / 36.0
    return True, cost, px + ox, py + oy, pz + oz


@numba.njit(cache=True, fastmath=_FASTMATH)
def _edge_cost_place(
    policy, u, v, V, F, face_alive, head, nxt, su, sv, mark, stamp, cA, cb, H, r
):  # pragma: no cover - numba
    """Cost and placement of edge (u, v) under ``policy``: ``(ok, cost, px, py, pz)``."""
    nu = _gather_star(u, F, face_alive, head, nxt, su)
    nv_ = _gather_star(v, F, face_alive, head, nxt, sv)
    if nu > su.shape[0] or nv_ > sv.shape[0]:
        return False, np.inf, 0.0, 0.0, 0.0
    if policy == POLICY_MEMORYLESS:
        return _lt_cost_place(u, v, V, F, su, nu, sv, nv_, mark, stamp, cA, cb, H, r)
    # POLICY_MIDPOINT
    px = 0.5 * (V[u, 0] + V[v, 0])
    py = 0.5 * (V[u, 1] + V[v, 1])
    pz = 0.5 * (V[u, 2] + V[v, 2])
    cost = (V[u, 0] - V[v, 0]) ** 2 + (V[u, 1] - V[v, 1]) ** 2 + (V[u, 2] - V[v, 2]) ** 2
    return True, cost, px, py, pz


@numba.njit(cache=True, fastmath=_FASTMATH)
def _push_edge(
    policy, u, v, version, keys, pay, size, V, F, face_alive, head, nxt, su, sv, mark, stamp,
    cA, cb, H, r,
):  # pragma: no cover - numba
    if u > v:
        u, v = v, u
    ok, cost, _, _, _ = _edge_cost_place(
        policy, u, v, V, F, face_alive, head, nxt, su, sv, mark, stamp, cA, cb, H, r
    )
    if not ok:
        return keys, pay, size
    return _heap_push(keys, pay, size, cost, u, v, version[u], version[v])
