"""Discrete curvature at a fan vertex [Dyn01] (spec Eq. 3) and the curvedness (numba kernels).

The formulas and their derivation: :func:`_curvature_at`.
"""

from __future__ import annotations

import math

import numba

from tumor3d.simplify._jit import _FASTMATH
from tumor3d.simplify._topology import _slot

# Cephes atan (S. L. Moshier, Cephes Math Library, atan.c): range reduction to
# |x| <= 0.66 and a (4, 5) rational approximation; max error ~2 ulp (measured
# against libm's atan2 on 5 M random arguments: 74 % identical, the rest 1-2 ulp)
_ATAN_P = (-8.750608600031904122785e-1, -1.615753718733365076637e1,
           -7.500855792314704667340e1, -1.228866684490136173410e2,
           -6.485021904942025371773e1)  # fmt: skip
_ATAN_Q = (2.485846490142306297962e1, 1.650270098316988542046e2,
           4.328810604912902668951e2, 4.853903996359136964868e2,
           1.945506571482613964425e2)  # fmt: skip
_TAN3PI8 = 2.414213562373095
_MOREBITS = 6.123233995736766e-17  # pi/2 - float(pi/2)


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _atan_nonneg(x):  # pragma: no cover - numba
    """``atan(x)`` for ``x >= 0`` (Cephes' reduction and rational approximation)."""
    if x > _TAN3PI8:
        y = 0.5 * math.pi
        x = -1.0 / x
        extra = _MOREBITS
    elif x <= 0.66:
        y = 0.0
        extra = 0.0
    else:
        y = 0.25 * math.pi
        x = (x - 1.0) / (x + 1.0)
        extra = 0.5 * _MOREBITS
    z = x * x
    p = (((_ATAN_P[0] * z + _ATAN_P[1]) * z + _ATAN_P[2]) * z + _ATAN_P[3]) * z + _ATAN_P[4]
    q = ((((z + _ATAN_Q[0]) * z + _ATAN_Q[1]) * z + _ATAN_Q[2]) * z + _ATAN_Q[3]) * z + _ATAN_Q[4]
    z = x * (z * p / q) + x
    return y + (z + extra)


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _angle(s, c):  # pragma: no cover - numba
    """The angle in ``[0, pi]`` with sine ``s >= 0`` and cosine ``c`` (any common scale)."""
    if c > 0.0:
        return _atan_nonneg(s / c)
    if c < 0.0:
        return math.pi - _atan_nonneg(s / -c)
    return 0.5 * math.pi if s > 0.0 else 0.0


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _face_terms(v, b, c, V, k, fbuf, ibuf, area, zr, zi, turns, n_pi):  # pragma: no cover
    """Add face ``(v, b, c)`` (row ``k``) to the sums of :func:`_curvature_at`."""
    vx = V[v, 0]
    vy = V[v, 1]
    vz = V[v, 2]
    e1x = V[b, 0] - vx
    e1y = V[b, 1] - vy
    e1z = V[b, 2] - vz
    e2x = V[c, 0] - vx
    e2y = V[c, 1] - vy
    e2z = V[c, 2] - vz
    cx = e1y * e2z - e1z * e2y
    cy = e1z * e2x - e1x * e2z
    cz = e1x * e2y - e1y * e2x
    norm = math.sqrt(cx * cx + cy * cy + cz * cz)
    dot = e1x * e2x + e1y * e2y + e1z * e2z
    area += 0.5 * norm
    if norm > 0.0:
        below = zi < 0.0
        t = zr * dot - zi * norm
        zi = zr * norm + zi * dot
        zr = t
        if below and zi >= 0.0:
            turns += 1
        m = abs(zr) + abs(zi)
        if m > 1e100 or m < 1e-100:
            e = math.frexp(m)[1]
            zr = math.ldexp(zr, -e)
            zi = math.ldexp(zi, -e)
    elif dot < 0.0:
        n_pi += 1
    fbuf[k, 0] = cx
    fbuf[k, 1] = cy
    fbuf[k, 2] = cz
    fbuf[k, 3] = math.sqrt(e1x * e1x + e1y * e1y + e1z * e1z)  # |e| of edge v-b
    fbuf[k, 4] = e1x
    fbuf[k, 5] = e1y
    fbuf[k, 6] = e1z
    ibuf[k, 0] = b
    ibuf[k, 1] = c
    return area, zr, zi, turns, n_pi


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _curvature_sums(n, fbuf, ibuf, area, zr, zi, turns, n_pi):  # pragma: no cover - numba
    """``(K, H, A)`` from the rows of :func:`_face_terms` (see :func:`_curvature_at`)."""
    if not area > 0.0:
        return 0.0, 0.0, 0.0
    arg = math.atan2(zi, zr)
    if zi < 0.0:
        turns += 1  # arg in (-pi, 0): the angle from the positive axis is arg + 2 pi
    deficit = (2.0 * (1 - turns) - n_pi) * math.pi - arg
    hsum = 0.0
    for k in range(n):
        b = ibuf[k, 0]
        for m in range(n):
            if ibuf[m, 1] == b:  # face m is the other face at edge v-b
                dn = fbuf[k, 0] * fbuf[m, 0] + fbuf[k, 1] * fbuf[m, 1] + fbuf[k, 2] * fbuf[m, 2]
                det = fbuf[m, 4] * fbuf[k, 0] + fbuf[m, 5] * fbuf[k, 1] + fbuf[m, 6] * fbuf[k, 2]
                le = fbuf[k, 3]
                hsum += le * _angle(abs(det) * le, dn)
                break
    third = area / 3.0
    return deficit / third, 0.25 * hsum / third, area


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _curvature_at(v, V, F, star, n, fbuf, ibuf):  # pragma: no cover - numba
    r"""Discrete Gaussian ``K`` and mean ``H`` curvature at a fan vertex [Dyn01] (Eq. 3).

    ``A = sum area(t_j)``, ``K = (2 pi - sum alpha_j) / (A / 3)``,
    ``H = 1/4 sum ||e_j|| beta_j / (A / 3)``, ``beta_j`` the unsigned angle
    between the normals of the two faces at edge ``e_j`` ([A18]). Returns
    ``(K, H, A)``; ``A = 0`` flags a degenerate star. ``fbuf`` (>= 7
    columns) and ``ibuf`` (2 columns) are scratch rows, one per face.

    The angles are computed with one library arctangent per vertex instead
    of two per face (the same quantities as Eq. 3, to rounding):

    * ``sum alpha_j``: with ``e1, e2`` the edges of ``t_j`` at ``v``, the
      complex number ``e1 . e2 + i |e1 x e2|`` has argument ``alpha_j`` in
      ``[0, pi]``; their running product turns counterclockwise by
      ``alpha_j`` per face, less than half a turn, so it crosses the
      positive real axis (from below) once per full turn. Counting those
      crossings unwraps the one ``atan2`` of the product:
      ``sum alpha_j = 2 pi turns + arg``, and ``2 pi - sum alpha_j`` is
      formed as ``2 pi (1 - turns) - arg`` without cancelling two ~2 pi
      terms. Zero-area faces (``alpha`` exactly 0 or pi) are counted
      apart; the product is rescaled by powers of two (exact) to stay in
      range.
    * ``beta_j`` at edge ``v-b`` between ``t_k = (v, b, c)`` and
      ``t_m = (v, a, b)`` with normals ``n_k = e_b x e_c``, ``n_m = e_a x
      e_b``: ``beta = atan2(|n_m x n_k|, n_m . n_k)`` and ``n_m x n_k =
      det[e_a, e_b, e_c] e_b``, so ``|n_m x n_k| = |e_a . n_k| ||e_b||``: no
      unit normals, and accurate near ``beta = 0`` where ``acos`` of a
      normalised dot product loses half the digits (~1e-8 rad of noise on
      flat patches). The arctangent is Cephes' rational approximation
      (:func:`_atan_nonneg`, within 2 ulp of libm), inlined.
    """
    area = 0.0
    zr = 1.0  # running product of (e1 . e2 + i |e1 x e2|)
    zi = 0.0
    turns = 0
    n_pi = 0  # zero-area faces with alpha = pi
    for k in range(n):
        f = star[k]
        r = _slot(F, f, v)
        area, zr, zi, turns, n_pi = _face_terms(
            v, F[f, (r + 1) % 3], F[f, (r + 2) % 3], V, k, fbuf, ibuf, area, zr, zi, turns, n_pi
        )
    return _curvature_sums(n, fbuf, ibuf, area, zr, zi, turns, n_pi)


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _curvature_walk(v, V, F, face_alive, head, nxt, fbuf, ibuf):  # pragma: no cover - numba
    """:func:`_gather_star` and :func:`_curvature_at` in one walk of ``v``'s corner list.

    The same faces in the same order, so the same ``(K, H, A)``; the loads
    of the list and of the face positions overlap. ``A = 0`` also when the
    star has more faces than ``fbuf`` has rows.
    """
    cap = fbuf.shape[0]
    area = 0.0
    zr = 1.0
    zi = 0.0
    turns = 0
    n_pi = 0
    c = head[v]
    prev = -1
    n = 0
    while c != -1:
        nc = nxt[c]
        f = c // 3
        r = c - 3 * f
        if face_alive[f] and F[f, r] == v:
            if prev == -1:
                head[v] = c
            else:
                nxt[prev] = c
            prev = c
            if n < cap:
                area, zr, zi, turns, n_pi = _face_terms(
                    v, F[f, (r + 1) % 3], F[f, (r + 2) % 3], V, n, fbuf, ibuf,
                    area, zr, zi, turns, n_pi,
                )  # fmt: skip
            n += 1
        c = nc
    if prev == -1:
        head[v] = -1
    else:
        nxt[prev] = -1
    if n > cap:
        return 0.0, 0.0, 0.0
    return _curvature_sums(n, fbuf, ibuf, area, zr, zi, turns, n_pi)


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _curvedness(K, H, no_root):  # pragma: no cover - numba
    """R = sqrt(max(0, 2 H^2 - K)) ([A17]); ``no_root``: max(0, 2 H^2 - K)."""
    r2 = 2.0 * H * H - K
    if r2 < 0.0:
        r2 = 0.0
    if no_root:
        return r2
    return math.sqrt(r2)
