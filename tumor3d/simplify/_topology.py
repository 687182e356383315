"""Mesh adjacency of the collapse engine: corner lists, stars, fans (numba kernels).

A vertex -> face adjacency as *corner lists*: corner ``c = 3 f + k`` is
slot ``k`` of face ``f``; ``head[v]`` is the first corner of vertex ``v``
and ``nxt[c]`` the next one (-1 ends a list). Dead faces are dropped from a
list lazily, the next time the list is walked (:func:`_gather_star`). The
lists are built by :func:`tumor3d.simplify._engine.build_corner_lists`.
"""

from __future__ import annotations

import numba
import numpy as np

from tumor3d.simplify._jit import _FASTMATH

# vertex status codes of _vertex_status
STATUS_OK = 0  #: the faces around the vertex form one closed, oriented fan
STATUS_PINCH = 1  #: several closed fans meet at the vertex (locked, never collapsed)
STATUS_DEFECT = 2  #: a boundary, non-manifold or inconsistently oriented edge, or a degenerate face


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _slot(F, f, v):  # pragma: no cover - numba
    if F[f, 0] == v:
        return 0
    if F[f, 1] == v:
        return 1
    if F[f, 2] == v:
        return 2
    return -1


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _gather_star(v, F, face_alive, head, nxt, out):  # pragma: no cover - numba
    """Write the live faces around ``v`` into ``out``; return their number.

    Dead corners are unlinked on the way. Returns ``out.shape[0] + 1`` when
    the star does not fit (the caller then refuses to touch ``v``).
    """
    c = head[v]
    prev = -1
    n = 0
    cap = out.shape[0]
    while c != -1:
        nc = nxt[c]
        f = c // 3
        if face_alive[f] and F[f, c % 3] == v:
            if n < cap:
                out[n] = f
            n += 1
            if prev == -1:
                head[v] = c
            else:
                nxt[prev] = c
            prev = c
        c = nc
    if prev == -1:
        head[v] = -1
    else:
        nxt[prev] = -1
    if n > cap:
        return cap + 1
    return n


@numba.njit(cache=True, fastmath=_FASTMATH)
def vertex_status(F, n_vertices, head, nxt):  # pragma: no cover - numba
    """Classify every vertex (``STATUS_*``) from the fan of its faces.

    For a face ``(v, b, c)`` (rotated to start at ``v``) record the step
    ``b -> c``. The star of ``v`` is one closed, consistently oriented fan iff
    the ``b`` are distinct, the ``c`` are distinct, both sets agree and
    following the steps from any face visits every face. Distinct ``b`` (and
    ``c``) means each directed edge at ``v`` is used once; equal sets means
    each undirected edge at ``v`` is used by two faces in opposite
    directions. When that holds at every vertex the mesh is closed, edge-
    manifold and oriented.
    """
    status = np.zeros(n_vertices, dtype=np.int64)
    alive = np.ones(F.shape[0], dtype=np.bool_)
    buf = np.empty(4096, dtype=np.int64)
    bs = np.empty(4096, dtype=np.int64)
    cs = np.empty(4096, dtype=np.int64)
    for v in range(n_vertices):
        n = _gather_star(v, F, alive, head, nxt, buf)
        if n == 0:
            continue
        if n > buf.shape[0]:
            status[v] = STATUS_PINCH
            continue
        bad = False
        for k in range(n):
            f = buf[k]
            r = _slot(F, f, v)
            b = F[f, (r + 1) % 3]
            c = F[f, (r + 2) % 3]
            if b == v or c == v or b == c:
                bad = True
            bs[k] = b
            cs[k] = c
        if bad:
            status[v] = STATUS_DEFECT
            continue
        for k in range(n):
            nb = 0
            nc = 0
            for m in range(n):
                if bs[m] == bs[k]:
                    nb += 1
                if cs[m] == bs[k]:
                    nc += 1
            if nb != 1 or nc != 1:
                bad = True
                break
        if bad:
            status[v] = STATUS_DEFECT
            continue
        # one cycle? follow b -> c starting from face 0
        steps = 1
        cur = cs[0]
        while cur != bs[0] and steps <= n:
            for m in range(n):
                if bs[m] == cur:
                    cur = cs[m]
                    break
            steps += 1
        if steps != n:
            status[v] = STATUS_PINCH
    return status


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _neighbours(v, F, star, n, out):  # pragma: no cover - numba
    """Neighbours of a fan vertex: the vertex after ``v`` in each face of its star."""
    for k in range(n):
        f = star[k]
        r = _slot(F, f, v)
        out[k] = F[f, (r + 1) % 3]
    return n
