"""The curvature scheduler's speed-ups change no result (issues 30 and 32).

* the indexed vertex heap pops in the order of ``(key, v)`` under inserts,
  key changes (ties included) and removals, like the lazy-deletion heap it
  replaced;
* int32 and int64 index arrays give the same mesh;
* the engine's Algorithm 2 loop gives the same mesh, bit for bit, as
  :func:`_reference_vertex_priority` below: the loop as it was before the
  speed-ups of the second round (each star re-gathered, every Eq. 6 cost from
  :func:`~tumor3d.simplify._engine._check_star_geometry`, the ring curvature
  from :func:`~tumor3d.simplify._engine._curvature_at`), kept as the naive
  reference of what the faster loop must reproduce.

The meshes themselves were compared bit for bit with the former kernel
(lazy-deletion heap, int64) when the change was made: the 1 M-face benchmark
mesh at P = 60 % and a 237 k-face one at P = 60 / 90 % (tau once and
refresh) and 40 % (no_root), identical (``reports/benchmarks.md``).
"""

from __future__ import annotations

import numba
import numpy as np
import pytest

from tumor3d.geometry.mesh import Mesh
from tumor3d.geometry.surface import extract_surface
from tumor3d.simplify import _engine
from tumor3d.simplify._prepare import DEFAULT_TOLERANCES, prepare


def _blob(seed: int) -> Mesh:
    rng = np.random.default_rng(seed)
    n = 30
    z, y, x = np.ogrid[:n, :n, :n]
    mask = np.zeros((n, n, n), bool)
    for _ in range(4):
        c = rng.uniform(8, n - 8, 3)
        r = rng.uniform(3.0, 7.0)
        mask |= (z - c[0]) ** 2 + (y - c[1]) ** 2 + (x - c[2]) ** 2 <= r * r
    return extract_surface(mask, np.diag([0.9, 0.9, 1.5, 1.0]))


def test_indexed_heap_pops_in_key_then_vertex_order():
    rng = np.random.default_rng(0)
    nv = 300
    hk = np.empty(nv)
    hv = np.empty(nv, dtype=np.int64)
    pos = np.full(nv, -1, dtype=np.int64)
    size = 0
    model: dict[int, float] = {}
    for _ in range(20_000):
        op = rng.random()
        v = int(rng.integers(nv))
        if op < 0.55:
            key = float(rng.integers(0, 12)) / 4.0  # many exact ties
            size = _engine._vheap_set(hk, hv, pos, size, v, key)
            model[v] = key
        elif op < 0.75:
            if v in model:
                size = _engine._vheap_remove(hk, hv, pos, size, v)
                del model[v]
        elif size > 0:
            top = int(hv[0])
            assert (hk[0], top) == min((k, u) for u, k in model.items())
            size = _engine._vheap_remove(hk, hv, pos, size, top)
            del model[top]
        assert size == len(model)
    assert all(pos[v] >= 0 for v in model)


def _engine_loop(mesh: Mesh, target: int, compact_index: bool):
    tol = DEFAULT_TOLERANCES
    arr = prepare(mesh, "curvature", compact_index=compact_index)
    assert arr.faces.dtype == (np.int32 if compact_index else np.int64)
    alive = _engine.run_vertex_priority(
        arr.vertices, arr.faces, arr.head, arr.nxt, arr.status, target, False,
        tol.max_star, tol.min_quality,
    )[0]  # fmt: skip
    return _engine.compact(arr.vertices, arr.faces, alive)


@pytest.mark.parametrize("seed", [1, 2])
@pytest.mark.parametrize("keep", [0.6, 0.2])
def test_int32_and_int64_indices_give_the_same_mesh(seed, keep):
    mesh = _blob(seed)
    target = int(mesh.n_faces * keep)
    ref_v, ref_f = _engine_loop(mesh, target, False)
    v, f = _engine_loop(mesh, target, True)
    assert np.array_equal(f, ref_f)
    assert np.array_equal(v, ref_v)


@numba.njit(cache=True)
def _reference_vertex_priority(V, F, head, nxt, status, target_faces, no_root, max_star, min_q):
    """Algorithm 2 as the engine ran it before the second round of speed-ups (naive reference)."""
    E = _engine
    nv = V.shape[0]
    face_alive = np.ones(F.shape[0], dtype=np.bool_)
    vertex_alive = np.ones(nv, dtype=np.bool_)
    locked = status != E.STATUS_OK
    cap = max_star + 8
    si = np.empty(cap, dtype=np.int64)
    sj = np.empty(cap, dtype=np.int64)
    sbuf = np.empty(cap, dtype=np.int64)
    ring = np.empty(cap, dtype=np.int64)
    fbuf = np.empty((cap, 4))
    ibuf = np.empty((cap, 2), dtype=np.int64)
    cand_j = np.empty(cap, dtype=np.int64)
    cand_f = np.empty((cap, 3))
    mark = np.zeros(nv, dtype=np.int64)
    stamp = np.zeros(1, dtype=np.int64)
    R = np.full(nv, np.inf)
    interior = np.zeros(nv, dtype=np.bool_)
    total = 0.0
    count = 0
    for v in range(nv):
        if locked[v]:
            continue
        n = E._gather_star(v, F, face_alive, head, nxt, sbuf)
        if n == 0 or n > max_star:
            locked[v] = True
            continue
        K, H, A = E._curvature_at(v, V, F, sbuf, n, fbuf, ibuf)
        if not A > 0.0:
            continue
        R[v] = E._curvedness(K, H, no_root)
        interior[v] = True
        total += R[v]
        count += 1
    tau = total / count if count > 0 else 0.0
    hk = np.empty(nv)
    hv = np.empty(nv, dtype=np.int64)
    pos = np.full(nv, -1, dtype=np.int64)
    size = 0
    for v in range(nv):
        if interior[v] and R[v] < tau:
            size = E._vheap_set(hk, hv, pos, size, v, R[v])
    n_faces = F.shape[0]
    n_collapses = 0
    while n_faces > target_faces and size > 0:
        vi = hv[0]
        size = E._vheap_remove(hk, hv, pos, size, vi)
        ni, s1 = E._prepare_i(vi, F, face_alive, head, nxt, mark, stamp, si)
        E._neighbours(vi, F, si, ni, ring)
        nc = 0
        for k in range(ni):
            j = ring[k]
            if locked[j]:
                continue
            px = V[j, 0]
            py = V[j, 1]
            pz = V[j, 2]
            ok, cost, sq = E._check_star_geometry(vi, j, px, py, pz, V, F, si, ni, True, min_q)
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
            nj = E._check_topology_j(
                vi, ni, si, s1, j, F, face_alive, locked, head, nxt, mark, sj, max_star
            )
            if nj >= 0:
                best_j = j
                break
            nc -= 1
            cand_j[b] = cand_j[nc]
            cand_f[b, 0] = cand_f[nc, 0]
            cand_f[b, 1] = cand_f[nc, 1]
            cand_f[b, 2] = cand_f[nc, 2]
        if best_j == -1:
            continue
        n_faces -= E._collapse(
            vi, best_j, V[best_j, 0], V[best_j, 1], V[best_j, 2],
            V, F, face_alive, vertex_alive, head, nxt, sbuf,
        )  # fmt: skip
        n_collapses += 1
        for k in range(ni):
            w = ring[k]
            if not vertex_alive[w] or locked[w]:
                continue
            n = E._gather_star(w, F, face_alive, head, nxt, sbuf)
            K, H, A = E._curvature_at(w, V, F, sbuf, n, fbuf, ibuf)
            if not A > 0.0:
                R[w] = np.inf
                if pos[w] >= 0:
                    size = E._vheap_remove(hk, hv, pos, size, w)
                continue
            R[w] = E._curvedness(K, H, no_root)
            if R[w] < tau:
                size = E._vheap_set(hk, hv, pos, size, w, R[w])
            elif pos[w] >= 0:
                size = E._vheap_remove(hk, hv, pos, size, w)
    return face_alive, n_faces, n_collapses, tau


@pytest.mark.parametrize(
    ("seed", "keep", "no_root"),
    [(1, 0.4, False), (2, 0.1, False), (3, 0.6, True), (4, 0.25, False)],
)
def test_loop_gives_the_naive_reference_mesh_bit_for_bit(seed, keep, no_root):
    mesh = _blob(seed)
    target = int(mesh.n_faces * keep)
    tol = DEFAULT_TOLERANCES
    ref = prepare(mesh, "curvature")
    alive, n_ref, coll_ref, tau_ref = _reference_vertex_priority(
        ref.vertices, ref.faces, ref.head, ref.nxt, ref.status, target, no_root,
        tol.max_star, tol.min_quality,
    )  # fmt: skip
    ref_v, ref_f = _engine.compact(ref.vertices, ref.faces, alive)
    arr = prepare(mesh, "curvature", compact_index=True)
    out = _engine.run_vertex_priority(
        arr.vertices, arr.faces, arr.head, arr.nxt, arr.status, target, no_root,
        tol.max_star, tol.min_quality,
    )  # fmt: skip
    v, f = _engine.compact(arr.vertices, arr.faces, out[0])
    assert (out[2], out[3], out[4]) == (n_ref, coll_ref, tau_ref)
    assert coll_ref > 0.3 * mesh.n_faces * (1 - keep)  # the loop did collapse
    assert np.array_equal(f, ref_f)
    assert np.array_equal(v, ref_v)
