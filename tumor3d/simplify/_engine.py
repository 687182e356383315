"""One edge-collapse engine on flat arrays (numba), shared by the simplifiers.

The mesh lives in a handful of flat arrays:

* ``V`` (n_vertices, 3) float64 positions (mm), ``F`` (n_faces, 3) int64
  triangles, ``face_alive`` / ``vertex_alive`` flags;
* a vertex -> face adjacency as *corner lists*: corner ``c = 3 f + k`` is
  slot ``k`` of face ``f``; ``head[v]`` is the first corner of vertex ``v``
  and ``nxt[c]`` the next one (-1 ends a list). Dead faces are dropped from a
  list lazily, the next time the list is walked (:func:`_gather_star`).

A collapse ``v_i -> v_j`` with new position ``p`` (:func:`_collapse`) deletes
the faces of the edge (two on a closed manifold), substitutes ``v_j`` for
``v_i`` in the rest of ``v_i``'s star (which keeps their orientation), moves
those corners to ``v_j``'s list, deletes ``v_i`` and puts ``v_j`` at ``p``.

:func:`_check_collapse_j` keeps a closed, oriented 2-manifold closed and
oriented (spec [A21]):

* the edge has exactly two faces, with distinct opposite vertices ``a, b``;
* link condition: ``N(v_i) & N(v_j) == {a, b}`` (Dey et al. 1999) and the
  two vertices are not a tetrahedron's (no face ``(v_i, a, b)`` together with
  ``(v_j, a, b)``), so no edge gets a third face and no face is doubled;
* no changed face flips: ``n(t) . n(t') > 0``;
* no degenerate face: ``|n(t')| > 1e-12 (l1^2 + l2^2 + l3^2)``;
* no needle: a changed face may not end below the quality ``S(t') <
  min_quality`` unless it was already that poor (``S(t') >= S(t)``);
* the star of the kept vertex stays below ``max_star`` faces (bounded
  valence, bounded scratch buffers).

Two schedulers drive the engine:

* :func:`run_vertex_priority` -- Algorithm 2 of the paper (vertex min-heap on
  the curvedness, cost ``sum V(t) (1 - S(t'))``, the kept vertex does not
  move);
* :func:`run_edge_priority` -- an edge min-heap whose cost and placement are
  chosen by ``policy`` (``POLICY_MEMORYLESS`` = Lindstrom-Turk); a new policy
  is one more branch in :func:`_edge_cost_place`.

:func:`run_vertex_priority` keeps its candidates in an indexed heap (one
entry per candidate vertex, ordered by ``(R, v)``); with ``lazy``, a
candidate whose star changed keeps its key until it reaches the top, where
its ``R`` is recomputed (the re-evaluation of stale priorities of QEM
implementations). :func:`run_edge_priority` uses lazy deletion (stale
entries are recognised and skipped when popped) and compacts the heap when
stale entries dominate, so memory stays ``O(n_faces)``.

Index arrays (``F``, ``head``, ``nxt``) may be int64 or int32; the curvature
simplifier passes int32 (half the memory traffic of the adjacency; it refuses a
mesh whose corners do not fit, ``_prepare.MAX_COMPACT_FACES``), the edge
scheduler and ``vertex_curvatures`` int64.

This module holds the kernels called from Python (the entry points); the
rest is split by concept: :mod:`~tumor3d.simplify._topology` (corner lists,
stars, vertex status), :mod:`~tumor3d.simplify._collapse` (validity checks
and the collapse), :mod:`~tumor3d.simplify._heap` (priority queues),
:mod:`~tumor3d.simplify._curvature_kernels` (Eq. 3),
:mod:`~tumor3d.simplify._edge_cost` (cost and placement of the edge
scheduler) and :mod:`~tumor3d.simplify._jit` (numba settings, the cache
hint, one cache stamp for all of these files).

References
----------
T. K. Dey, H. Edelsbrunner, S. Guha, D. V. Nekhayev, "Topology preserving
edge contraction", Publ. Inst. Math. (Beograd) 66, 1999.
P. Lindstrom, G. Turk, "Fast and memory efficient polygonal simplification",
IEEE Visualization 1998, doi:10.1109/VISUAL.1998.745314.
N. Dyn, K. Hormann, S.-J. Kim, D. Levin, "Optimizing 3D triangulations using
discrete curvature analysis", Mathematical Methods for Curves and Surfaces,
2001.
"""

from __future__ import annotations

import numba
import numpy as np

from tumor3d.simplify._collapse import (
    _check_collapse_j,
    _check_star_geometry,
    _check_topology_j,
    _collapse,
    _collapse_star,
    _prepare_i,
    _star_geometry_table,
    _star_table,
)
from tumor3d.simplify._curvature_kernels import _curvature_at, _curvature_walk, _curvedness
from tumor3d.simplify._edge_cost import (
    POLICY_MEMORYLESS,
    POLICY_MIDPOINT,
    _edge_cost_place,
    _push_edge,
)
from tumor3d.simplify._heap import (
    _heap_pop,
    _heapify,
    _vheap_down,
    _vheap_pop,
    _vheap_remove,
    _vheap_set,
)
from tumor3d.simplify._jit import _FASTMATH, _prefetch
from tumor3d.simplify._topology import (
    STATUS_DEFECT,
    STATUS_OK,
    STATUS_PINCH,
    _gather_star,
    _neighbours,
    vertex_status,
)

# the engine's names for its callers (simplifiers, tests): one module to import
__all__ = [
    "POLICY_MEMORYLESS", "POLICY_MIDPOINT", "STATUS_DEFECT", "STATUS_OK", "STATUS_PINCH",
    "build_corner_lists", "compact", "curvatures", "run_edge_priority", "run_vertex_priority",
    "vertex_status", "_check_star_geometry",
]  # fmt: skip


@numba.njit(cache=True, fastmath=_FASTMATH)
def build_corner_lists(faces: np.ndarray, n_vertices: int):  # pragma: no cover - numba
    """Vertex -> corner linked lists ``(head, nxt)`` of a face array."""
    n_corners = 3 * faces.shape[0]
    head = np.full(n_vertices, -1, dtype=faces.dtype)
    nxt = np.full(n_corners, -1, dtype=faces.dtype)
    for c in range(n_corners - 1, -1, -1):
        v = faces[c // 3, c % 3]
        nxt[c] = head[v]
        head[v] = c
    return head, nxt


@numba.njit(cache=True, fastmath=_FASTMATH)
def curvatures(V, F, head, nxt, status, max_star):  # pragma: no cover - numba
    """``(K, H, A)`` at every ``STATUS_OK`` vertex (NaN elsewhere)."""
    nv = V.shape[0]
    out = np.full((nv, 3), np.nan)
    alive = np.ones(F.shape[0], dtype=np.bool_)
    star = np.empty(max_star, dtype=np.int64)
    fbuf = np.empty((max_star, 7))
    ibuf = np.empty((max_star, 2), dtype=np.int64)
    for v in range(nv):
        if status[v] != STATUS_OK:
            continue
        n = _gather_star(v, F, alive, head, nxt, star)
        if n == 0 or n > max_star:
            continue
        K, H, A = _curvature_at(v, V, F, star, n, fbuf, ibuf)
        if A > 0.0:
            out[v, 0] = K
            out[v, 1] = H
            out[v, 2] = A
    return out


@numba.njit(cache=True, fastmath=_FASTMATH)
def run_vertex_priority(
    V, F, head, nxt, status, target_faces, no_root, max_star, min_quality, lazy
):  # pragma: no cover - numba
    """Algorithm 2 of the paper on the engine (spec section 6).

    ``V``, ``F``, ``head``, ``nxt`` are modified in place (the caller passes
    copies). Returns ``(face_alive, vertex_alive, n_faces, n_collapses,
    tau, n_candidates0, n_pops)``; ``n_pops`` counts the candidates taken
    from the heap and tried (collapsed or dropped, [A23]).

    The candidate set ``C`` is the heap's content. With ``lazy`` step 6 is
    applied lazily to the ring vertices that are in ``C``: such a vertex
    keeps its key (its ``R`` before the collapse) and is marked stale; when
    a stale vertex reaches the top, its ``R`` is recomputed on the current
    mesh and it leaves ``C`` (``R >= tau``) or takes its new key, and it is
    collapsed only when it is at the top with a current key. A ring vertex
    outside ``C`` is recomputed at once and enters ``C`` when ``R < tau``,
    as in the paper. The difference from the paper's (eager) step 6 is the
    order of pops: a candidate whose ``R`` fell is tried at its older,
    larger key, one whose ``R`` rose is put back. Without ``lazy``, every
    ring vertex is recomputed after each collapse (the paper's order).
    """
    nv = V.shape[0]
    nf = F.shape[0]
    face_alive = np.ones(nf, dtype=np.bool_)
    vertex_alive = np.ones(nv, dtype=np.bool_)
    locked = status != STATUS_OK
    cap = max_star + 8
    si = np.empty(cap, dtype=np.int64)
    sj = np.empty(cap, dtype=np.int64)
    sbuf = np.empty(cap, dtype=np.int64)
    ring = np.empty(cap, dtype=np.int64)
    fbuf = np.empty((cap, 7))
    ibuf = np.empty((cap, 2), dtype=np.int64)
    cand_j = np.empty(cap, dtype=np.int64)
    cand_f = np.empty((cap, 3))
    gab = np.empty((cap, 2), dtype=np.int64)
    gs = np.empty((cap, 9))
    mark = np.zeros(nv, dtype=np.int64)
    stamp = np.zeros(1, dtype=np.int64)

    # steps 1-2: R at interior vertices, tau = their mean (once, [A22])
    R = np.full(nv, np.inf)
    interior = np.zeros(nv, dtype=np.bool_)
    total = 0.0
    count = 0
    for v in range(nv):
        if locked[v]:
            continue
        n = _gather_star(v, F, face_alive, head, nxt, sbuf)
        if n == 0 or n > max_star:
            locked[v] = True
            continue
        K, H, A = _curvature_at(v, V, F, sbuf, n, fbuf, ibuf)
        if not A > 0.0:
            continue
        R[v] = _curvedness(K, H, no_root)
        interior[v] = True
        total += R[v]
        count += 1
    tau = total / count if count > 0 else 0.0
    # steps 3-4: candidates and their heap (indexed: one entry per candidate, keyed by (R, v))
    stale = np.zeros(nv, dtype=np.bool_)  # candidate whose star changed since R was computed
    hk = np.empty(nv)
    hv = np.empty(nv, dtype=F.dtype)
    pos = np.full(nv, -1, dtype=F.dtype)
    size = 0
    for v in range(nv):
        if interior[v] and R[v] < tau:
            hk[size] = R[v]
            hv[size] = v
            pos[v] = size
            size += 1
    n_cand0 = size
    for p in range(size // 2 - 1, -1, -1):
        _vheap_down(hk, hv, pos, size, p, hk[p], hv[p])
    n_faces = nf
    n_collapses = 0
    n_pops = 0
    # step 5
    while n_faces > target_faces and size > 0:
        vi = hv[0]
        ni, s1 = _prepare_i(vi, F, face_alive, head, nxt, mark, stamp, si)
        if stale[vi]:
            # step 6, deferred: R(v_i) is computed now that v_i reached the top
            stale[vi] = False
            K, H, A = _curvature_at(vi, V, F, si, ni, fbuf, ibuf)
            ri = _curvedness(K, H, no_root) if A > 0.0 else np.inf
            if not ri < tau:
                size = _vheap_pop(hk, hv, pos, size)  # v_i leaves C
                continue
            # the top with its current key: sift it down (same pops as remove + push)
            _vheap_down(hk, hv, pos, size, 0, ri, vi)
            if hv[0] != vi:
                continue
        size = _vheap_pop(hk, hv, pos, size)
        n_pops += 1
        # prefetches (results unchanged): the next top's first loads now, the
        # next links of its corner list and of the ring's lists later, when the
        # loads before them have arrived; 15 % of this loop's time on 1 M faces
        if size > 0:
            _prefetch(head, hv[0])
            _prefetch(V, 3 * hv[0])
        _neighbours(vi, F, si, ni, ring)
        # Eq. 6 cost of every edge whose geometry is valid (star of v_i only), then
        # the topological checks in order of increasing (cost, sum(1 - S), length, j)
        # ([A24]) until one passes: the same choice as checking every edge, cheaper
        nc = 0
        if ni <= si.shape[0]:
            _star_table(vi, V, F, si, ni, gab, gs)
        vix = V[vi, 0]
        viy = V[vi, 1]
        viz = V[vi, 2]
        for k in range(ni):
            j = ring[k]
            _prefetch(pos, j)
            _prefetch(head, j)
            if locked[j]:
                continue
            px = V[j, 0]
            py = V[j, 1]
            pz = V[j, 2]
            ok, cost, sq = _star_geometry_table(
                j, vix, viy, viz, px, py, pz, gab, gs, ni, min_quality
            )
            if not ok:
                continue
            cand_j[nc] = j
            cand_f[nc, 0] = cost
            cand_f[nc, 1] = sq
            cand_f[nc, 2] = (px - V[vi, 0]) ** 2 + (py - V[vi, 1]) ** 2 + (pz - V[vi, 2]) ** 2
            nc += 1
        best_j = -1
        while nc > 0:
            b = 0
            for k in range(1, nc):
                if cand_f[k, 0] != cand_f[b, 0]:
                    better = cand_f[k, 0] < cand_f[b, 0]
                elif cand_f[k, 1] != cand_f[b, 1]:
                    better = cand_f[k, 1] < cand_f[b, 1]
                elif cand_f[k, 2] != cand_f[b, 2]:
                    better = cand_f[k, 2] < cand_f[b, 2]
                else:
                    better = cand_j[k] < cand_j[b]
                if better:
                    b = k
            j = cand_j[b]
            nj = _check_topology_j(
                vi, ni, si, s1, j, F, face_alive, locked, head, nxt, mark, sj, max_star
            )
            if nj >= 0:
                best_j = j
                break
            nc -= 1  # drop candidate b
            cand_j[b] = cand_j[nc]
            cand_f[b, 0] = cand_f[nc, 0]
            cand_f[b, 1] = cand_f[nc, 1]
            cand_f[b, 2] = cand_f[nc, 2]
        if best_j == -1:
            continue  # v_i left C ([A23])
        if size > 0:
            c = head[hv[0]]
            if c >= 0:
                _prefetch(nxt, c)
                _prefetch(F, 3 * (c // 3))
        for k in range(ni):
            c = head[ring[k]]
            if c >= 0:
                _prefetch(nxt, c)
                _prefetch(F, 3 * (c // 3))
        # the star of v_i is still si[:ni]: the checks only walked v_j's list
        n_faces -= _collapse_star(
            vi, best_j, V[best_j, 0], V[best_j, 1], V[best_j, 2],
            V, F, face_alive, vertex_alive, head, nxt, si, ni,
        )  # fmt: skip
        n_collapses += 1
        # step 6 on the old ring N(v_i) (it contains v_j): with lazy, a candidate's R
        # is recomputed when it reaches the top (stale), any other vertex's now
        for k in range(ni):
            w = ring[k]
            if not vertex_alive[w] or locked[w]:
                continue
            if lazy and pos[w] >= 0:
                stale[w] = True
                continue
            K, H, A = _curvature_walk(w, V, F, face_alive, head, nxt, fbuf, ibuf)
            rw = _curvedness(K, H, no_root) if A > 0.0 else np.inf
            if rw < tau:
                size = _vheap_set(hk, hv, pos, size, w, rw)  # w enters C (or is re-keyed)
            elif pos[w] >= 0:
                size = _vheap_remove(hk, hv, pos, size, w)  # w leaves C
        if size > 0:
            c = head[hv[0]]
            if c >= 0:
                c = nxt[c]
                if c >= 0:
                    _prefetch(nxt, c)
                    _prefetch(F, 3 * (c // 3))
    return face_alive, vertex_alive, n_faces, n_collapses, tau, n_cand0, n_pops


@numba.njit(cache=True, fastmath=_FASTMATH)
def run_edge_priority(
    V, F, head, nxt, status, target_faces, policy, max_star, min_quality
):  # pragma: no cover - numba
    """Greedy edge collapse by increasing ``policy`` cost with its placement.

    Each heap entry is ``(cost, u, v, version[u], version[v])``; a collapse
    bumps the version of every vertex whose star changed, which makes the
    old entries of their edges stale, and pushes the edges around them
    again. An edge that fails the validity checks when popped is dropped
    until its neighbourhood changes. Returns ``(face_alive, vertex_alive,
    n_faces, n_collapses, n_pops)``.
    """
    nv = V.shape[0]
    nf = F.shape[0]
    face_alive = np.ones(nf, dtype=np.bool_)
    vertex_alive = np.ones(nv, dtype=np.bool_)
    locked = status != STATUS_OK
    cap = max_star + 8
    su = np.empty(cap, dtype=np.int64)
    sv = np.empty(cap, dtype=np.int64)
    si = np.empty(cap, dtype=np.int64)
    sj = np.empty(cap, dtype=np.int64)
    sbuf = np.empty(cap, dtype=np.int64)
    sbuf2 = np.empty(cap, dtype=np.int64)
    ring = np.empty(cap, dtype=np.int64)
    nbrs = np.empty(cap, dtype=np.int64)
    mark = np.zeros(nv, dtype=np.int64)
    ring_mark = np.zeros(nv, dtype=np.int64)
    stamp = np.zeros(1, dtype=np.int64)
    version = np.zeros(nv, dtype=np.int64)
    cA = np.zeros((3, 3))
    cb = np.zeros(3)
    H = np.zeros((3, 3))
    r = np.zeros(3)
    for v in range(nv):
        if not locked[v]:
            n = _gather_star(v, F, face_alive, head, nxt, sbuf)
            if n == 0 or n > max_star:
                locked[v] = True
    init = 3 * nf // 2 + 16
    keys = np.empty(init)
    pay = np.empty((init, 4), dtype=np.int64)
    size = np.int64(0)  # not the literal 0, nor below (_heap's docstring)
    for u in range(nv):
        if locked[u]:
            continue
        n = _gather_star(u, F, face_alive, head, nxt, sbuf2)
        _neighbours(u, F, sbuf2, n, nbrs)
        for k in range(n):
            w = nbrs[k]
            if w > u and not locked[w]:
                keys, pay, size = _push_edge(
                    policy, u, w, version, keys, pay, size, V, F, face_alive, head, nxt,
                    su, sv, mark, stamp, cA, cb, H, r,
                )  # fmt: skip
    n_live_edges = size
    n_faces = nf
    n_collapses = 0
    n_pops = 0
    ring_stamp = 0
    while n_faces > target_faces and size > 0:
        u = pay[0, 0]
        v = pay[0, 1]
        eu = pay[0, 2]
        ev = pay[0, 3]
        size = _heap_pop(keys, pay, size)
        n_pops += 1
        if not vertex_alive[u] or not vertex_alive[v] or version[u] != eu or version[v] != ev:
            continue
        ok, cost, px, py, pz = _edge_cost_place(
            policy, u, v, V, F, face_alive, head, nxt, su, sv, mark, stamp, cA, cb, H, r
        )
        if not ok:
            continue
        ni, s1 = _prepare_i(u, F, face_alive, head, nxt, mark, stamp, si)
        ok, _, _ = _check_collapse_j(
            u, ni, si, s1, v, px, py, pz, True, V, F, face_alive, locked, head, nxt,
            mark, sj, max_star, min_quality,
        )  # fmt: skip
        if not ok:
            continue
        n_faces -= _collapse(u, v, px, py, pz, V, F, face_alive, vertex_alive, head, nxt, sbuf)
        n_collapses += 1
        # the new star of v and its neighbours changed: bump versions, push their edges
        n = _gather_star(v, F, face_alive, head, nxt, sbuf)
        _neighbours(v, F, sbuf, n, ring)
        ring[n] = v
        nring = n + 1
        ring_stamp += 1
        for k in range(nring):
            version[ring[k]] += 1
            ring_mark[ring[k]] = ring_stamp
        for k in range(nring):
            w = ring[k]
            if locked[w]:
                continue
            m = _gather_star(w, F, face_alive, head, nxt, sbuf2)
            _neighbours(w, F, sbuf2, m, nbrs)
            for t in range(m):
                x = nbrs[t]
                if locked[x] or (ring_mark[x] == ring_stamp and x < w):
                    continue
                keys, pay, size = _push_edge(
                    policy, w, x, version, keys, pay, size, V, F, face_alive, head, nxt,
                    su, sv, mark, stamp, cA, cb, H, r,
                )  # fmt: skip
        # compaction: drop stale entries once they outnumber the live edges 2:1
        n_live_edges -= 3
        if size > 3 * max(n_live_edges, 1024):
            keep = np.int64(0)
            for e in range(size):
                a = pay[e, 0]
                b = pay[e, 1]
                fresh = version[a] == pay[e, 2] and version[b] == pay[e, 3]
                if vertex_alive[a] and vertex_alive[b] and fresh:
                    keys[keep] = keys[e]
                    for c in range(4):
                        pay[keep, c] = pay[e, c]
                    keep += 1
            size = keep
            n_live_edges = keep
            _heapify(keys, pay, size)
    return face_alive, vertex_alive, n_faces, n_collapses, n_pops


@numba.njit(cache=True, fastmath=_FASTMATH)
def compact(V, F, face_alive):  # pragma: no cover - numba
    """Live faces and the vertices they use, renumbered in order."""
    nv = V.shape[0]
    used = np.zeros(nv, dtype=np.bool_)
    n_f = 0
    for f in range(F.shape[0]):
        if face_alive[f]:
            n_f += 1
            for k in range(3):
                used[F[f, k]] = True
    remap = np.full(nv, -1, dtype=np.int64)
    n_v = 0
    for v in range(nv):
        if used[v]:
            remap[v] = n_v
            n_v += 1
    out_v = np.empty((n_v, 3))
    for v in range(nv):
        if used[v]:
            for k in range(3):  # not a row copy (_heap's docstring)
                out_v[remap[v], k] = V[v, k]
    out_f = np.empty((n_f, 3), dtype=np.int64)
    m = 0
    for f in range(F.shape[0]):
        if face_alive[f]:
            for k in range(3):
                out_f[m, k] = remap[F[f, k]]
            m += 1
    return out_v, out_f
