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
method passes int32 when the corners fit (half the memory traffic of the
adjacency, the same results).

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

import math

import numba
import numpy as np
from llvmlite import ir
from numba.core import cgutils, types
from numba.extending import intrinsic

POLICY_MEMORYLESS = 0  #: Lindstrom-Turk memoryless cost and placement
POLICY_MIDPOINT = 1  #: squared edge length, midpoint placement (engine tests)

#: LLVM fast-math flags without "no NaN / no inf" (the engine uses inf as a sentinel)
_FASTMATH: set[str] = set()
_SQRT3x4 = 4.0 * math.sqrt(3.0)
_COS2_ALPHA = math.cos(math.radians(1.0)) ** 2  # Lindstrom-Turk alpha = 1 degree
_SIN2_ALPHA = math.sin(math.radians(1.0)) ** 2

# vertex status codes of _vertex_status
STATUS_OK = 0  #: the faces around the vertex form one closed, oriented fan
STATUS_PINCH = 1  #: several closed fans meet at the vertex (locked, never collapsed)
STATUS_DEFECT = 2  #: a boundary, non-manifold or inconsistently oriented edge, or a degenerate face


# ---------------------------------------------------------------------------
# adjacency
# ---------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------
# cache hints
# ---------------------------------------------------------------------------


@intrinsic
def _prefetch(typingctx, arr, idx):  # pragma: no cover - compiled into the caller
    """Ask the CPU to bring flat element ``idx`` of the C-contiguous ``arr`` into its caches.

    LLVM's ``llvm.prefetch`` (read, high locality): a hint without any effect on
    the results; an index outside the array loads nothing and cannot fault.
    The collapse loop is bound by the latency of scattered loads (the heap
    pops vertices in curvedness order, anywhere on the mesh, and each star is
    a linked list walked load after load): it names the loads of the next
    iterations while the current one computes (:func:`run_vertex_priority`).
    """
    if not isinstance(arr, types.Array) or arr.layout != "C" or not isinstance(idx, types.Integer):
        return None
    sig = types.void(arr, idx)

    def codegen(context, builder, signature, args):  # type: ignore[no-untyped-def]
        ary = context.make_array(signature.args[0])(context, builder, args[0])
        i8p = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        fnty = ir.FunctionType(ir.VoidType(), [i8p, i32, i32, i32])
        fn = cgutils.get_or_insert_function(builder.module, fnty, "llvm.prefetch.p0i8")
        ptr = builder.bitcast(builder.gep(ary.data, [args[1]]), i8p)
        builder.call(fn, [ptr, i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return sig, codegen


# ---------------------------------------------------------------------------
# small geometry helpers
# ---------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------
# validity and the collapse itself
# ---------------------------------------------------------------------------


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


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _neighbours(v, F, star, n, out):  # pragma: no cover - numba
    """Neighbours of a fan vertex: the vertex after ``v`` in each face of its star."""
    for k in range(n):
        f = star[k]
        r = _slot(F, f, v)
        out[k] = F[f, (r + 1) % 3]
    return n


# ---------------------------------------------------------------------------
# binary min-heap (key, a, b, c, d), ordered by (key, a, b)
# ---------------------------------------------------------------------------


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _less(keys, pay, x, y):  # pragma: no cover - numba
    if keys[x] != keys[y]:
        return keys[x] < keys[y]
    if pay[x, 0] != pay[y, 0]:
        return pay[x, 0] < pay[y, 0]
    return pay[x, 1] < pay[y, 1]


@numba.njit(cache=True, fastmath=_FASTMATH)
def _swap(keys, pay, x, y):  # pragma: no cover - numba
    t = keys[x]
    keys[x] = keys[y]
    keys[y] = t
    for c in range(pay.shape[1]):
        u = pay[x, c]
        pay[x, c] = pay[y, c]
        pay[y, c] = u


@numba.njit(cache=True, fastmath=_FASTMATH)
def _sift_down(keys, pay, size, pos):  # pragma: no cover - numba
    while True:
        left = 2 * pos + 1
        if left >= size:
            return
        best = left
        right = left + 1
        if right < size and _less(keys, pay, right, left):
            best = right
        if _less(keys, pay, best, pos):
            _swap(keys, pay, best, pos)
            pos = best
        else:
            return


@numba.njit(cache=True, fastmath=_FASTMATH)
def _heap_push(keys, pay, size, key, p0, p1, p2, p3):  # pragma: no cover - numba
    """Push; returns the (possibly grown) arrays and the new size."""
    if size == keys.shape[0]:
        nk = np.empty(2 * size + 16, dtype=np.float64)
        npay = np.empty((2 * size + 16, pay.shape[1]), dtype=np.int64)
        nk[:size] = keys[:size]
        npay[:size] = pay[:size]
        keys = nk
        pay = npay
    pos = size
    keys[pos] = key
    pay[pos, 0] = p0
    pay[pos, 1] = p1
    pay[pos, 2] = p2
    pay[pos, 3] = p3
    size += 1
    while pos > 0:
        parent = (pos - 1) // 2
        if _less(keys, pay, pos, parent):
            _swap(keys, pay, pos, parent)
            pos = parent
        else:
            break
    return keys, pay, size


@numba.njit(cache=True, fastmath=_FASTMATH)
def _heap_pop(keys, pay, size):  # pragma: no cover - numba
    """Move the minimum to slot ``size - 1`` and restore the heap; return the new size."""
    size -= 1
    _swap(keys, pay, 0, size)
    _sift_down(keys, pay, size, 0)
    return size


@numba.njit(cache=True, fastmath=_FASTMATH)
def _heapify(keys, pay, size):  # pragma: no cover - numba
    for pos in range(size // 2 - 1, -1, -1):
        _sift_down(keys, pay, size, pos)


# ---------------------------------------------------------------------------
# indexed binary min-heap of vertices on (key, v): one entry per vertex
# ---------------------------------------------------------------------------


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _vless(ka, va, kb, vb):  # pragma: no cover - numba
    if ka != kb:
        return ka < kb
    return va < vb


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _vheap_up(hk, hv, pos, p, key, v):  # pragma: no cover - numba
    """Move the hole at ``p`` up until ``(key, v)`` fits, and put it there."""
    while p > 0:
        parent = (p - 1) >> 1
        if _vless(key, v, hk[parent], hv[parent]):
            hk[p] = hk[parent]
            hv[p] = hv[parent]
            pos[hv[p]] = p
            p = parent
        else:
            break
    hk[p] = key
    hv[p] = v
    pos[v] = p


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _vheap_down(hk, hv, pos, size, p, key, v):  # pragma: no cover - numba
    """Move the hole at ``p`` down until ``(key, v)`` fits, and put it there."""
    while True:
        c = 2 * p + 1
        if c >= size:
            break
        if c + 1 < size and _vless(hk[c + 1], hv[c + 1], hk[c], hv[c]):
            c += 1
        if _vless(hk[c], hv[c], key, v):
            hk[p] = hk[c]
            hv[p] = hv[c]
            pos[hv[p]] = p
            p = c
        else:
            break
    hk[p] = key
    hv[p] = v
    pos[v] = p


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _vheap_remove(hk, hv, pos, size, v):  # pragma: no cover - numba
    """Remove ``v`` (which must be in the heap); return the new size."""
    p = pos[v]
    pos[v] = -1
    size -= 1
    if p == size:
        return size
    key = hk[size]
    w = hv[size]
    if p > 0 and _vless(key, w, hk[(p - 1) >> 1], hv[(p - 1) >> 1]):
        _vheap_up(hk, hv, pos, p, key, w)
    else:
        _vheap_down(hk, hv, pos, size, p, key, w)
    return size


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _vheap_pop(hk, hv, pos, size):  # pragma: no cover - numba
    """Remove the top; return the new size.

    Floyd's variant of :func:`_vheap_remove` at the top: the hole goes down
    to a leaf along the smaller children (one comparison per level) and the
    last entry comes up from there (usually a step or two).
    """
    pos[hv[0]] = -1
    size -= 1
    if size == 0:
        return size
    key = hk[size]
    w = hv[size]
    p = 0
    while True:
        c = 2 * p + 1
        if c >= size:
            break
        if c + 1 < size and _vless(hk[c + 1], hv[c + 1], hk[c], hv[c]):
            c += 1
        hk[p] = hk[c]
        hv[p] = hv[c]
        pos[hv[p]] = p
        p = c
    _vheap_up(hk, hv, pos, p, key, w)
    return size


@numba.njit(cache=True, fastmath=_FASTMATH, inline="always")
def _vheap_set(hk, hv, pos, size, v, key):  # pragma: no cover - numba
    """Insert ``v`` with ``key``, or change its key; return the new size."""
    p = pos[v]
    if p < 0:
        _vheap_up(hk, hv, pos, size, key, v)
        return size + 1
    if p > 0 and _vless(key, v, hk[(p - 1) >> 1], hv[(p - 1) >> 1]):
        _vheap_up(hk, hv, pos, p, key, v)
    else:
        _vheap_down(hk, hv, pos, size, p, key, v)
    return size


# ---------------------------------------------------------------------------
# discrete curvature [Dyn01] (spec Eq. 3)
# ---------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------
# scheduler 1: Algorithm 2 (vertex priority on curvedness)
# ---------------------------------------------------------------------------


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


# ---------------------------------------------------------------------------
# scheduler 2: edge priority with a pluggable cost and placement
# ---------------------------------------------------------------------------


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
    size = 0
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
            keep = 0
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
            out_v[remap[v]] = V[v]
    out_f = np.empty((n_f, 3), dtype=np.int64)
    m = 0
    for f in range(F.shape[0]):
        if face_alive[f]:
            for k in range(3):
                out_f[m, k] = remap[F[f, k]]
            m += 1
    return out_v, out_f
