"""The curvature scheduler's speed-ups change no result (issues 30 and 32).

* the indexed vertex heap pops in the order of ``(key, v)`` under inserts,
  key changes (ties included) and removals (anywhere, and of the top by
  Floyd's pop), like the lazy-deletion heap it replaced;
* the engine's int32 input (the curvature method's) holds the int64 one's
  values, and a mesh whose corners do not fit in int32 is refused in one line;
* the engine's Algorithm 2 loop gives the same mesh, bit for bit, as
  :func:`_reference_vertex_priority` below: the loop written naively (each
  star re-gathered, every Eq. 6 cost from
  :func:`~tumor3d.simplify._engine._check_star_geometry`, the ring curvature
  from a gathered star, a stale candidate removed from the heap, recomputed
  and pushed back), kept as the reference of what the faster loop (one walk
  for gather and curvature, the stale top re-keyed in place and collapsed at
  once when it stays on top, the cache prefetches of the next pops) must
  reproduce;
* the prefetch hint reads nothing into the program: a kernel with and
  without it returns the same values and leaves the arrays as they were,
  also for an index outside the array;
* Eq. 3 as the engine computes it (one ``atan2`` of a running complex
  product for the angle sum, ``beta`` from ``det`` and Cephes' arctangent)
  agrees with the textbook sums (one ``atan2`` per face angle, ``acos`` of the
  unit normals), also where the angle sum passes several full turns.

Steps of the loop that changed the output (the Eq. 3 formula and the lazy
step 6, reports/benchmarks.md) were measured against Figure 10 on the
phantoms and BraTS cases; the reference follows the same definition.
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
            if op < 0.9:
                size = _engine._vheap_remove(hk, hv, pos, size, top)
            else:
                size = _engine._vheap_pop(hk, hv, pos, size)
            assert pos[top] == -1
            del model[top]
        assert size == len(model)
    assert all(pos[v] >= 0 for v in model)


def test_int32_input_holds_the_int64_values():
    """The curvature method's compact input is the wide one narrowed: the same faces,
    corner lists and vertex status (the engine computes in int64 either way)."""
    mesh = _blob(1)
    wide = prepare(mesh, "curvature")
    arr = prepare(mesh, "curvature", compact_index=True)
    assert wide.faces.dtype == np.int64 and arr.faces.dtype == np.int32
    for name in ("faces", "head", "nxt", "status"):
        a, w = getattr(arr, name), getattr(wide, name)
        assert np.array_equal(a.astype(np.int64), w.astype(np.int64)), name
    assert np.array_equal(arr.vertices, wide.vertices)


def test_a_mesh_too_large_for_int32_corners_is_refused(monkeypatch):
    """Beyond ``MAX_COMPACT_FACES`` (715,827,882 faces: 3 corners each in int32) the
    curvature method stops in one line instead of overflowing its indices; the limit is
    lowered here to a small mesh's size to reach the check."""
    from tumor3d.errors import InputError
    from tumor3d.simplify import _prepare
    from tumor3d.simplify.curvature import simplify_curvature

    assert _prepare.MAX_COMPACT_FACES == 715_827_882
    assert 3 * _prepare.MAX_COMPACT_FACES <= np.iinfo(np.int32).max
    assert 3 * (_prepare.MAX_COMPACT_FACES + 1) > np.iinfo(np.int32).max
    mesh = _blob(2)
    monkeypatch.setattr(_prepare, "MAX_COMPACT_FACES", mesh.n_faces - 1)
    with pytest.raises(InputError, match=f"{mesh.n_faces:,} faces.*method='qem'"):
        simplify_curvature(mesh, target_faces=mesh.n_faces // 2)
    monkeypatch.setattr(_prepare, "MAX_COMPACT_FACES", mesh.n_faces)
    assert simplify_curvature(mesh, target_faces=mesh.n_faces // 2).n_faces < mesh.n_faces


def _reference_vertex_priority(
    V, F, head, nxt, status, target_faces, no_root, max_star, min_q, lazy
):
    """Algorithm 2 (step 6 lazy or eager) written naively: the reference of the engine's loop.

    Plain Python around the engine's jitted steps (gather, curvature, checks, collapse,
    heap), called with the index type the product uses (int32): a jitted copy of this
    loop took ~15 CPU-s to compile on every new numba cache (each CI run), the loop
    itself runs in hundredths of a second on these meshes.
    """
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
    fbuf = np.empty((cap, 7))
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
    stale = np.zeros(nv, dtype=np.bool_)
    size = 0
    for v in range(nv):
        if interior[v] and R[v] < tau:
            size = E._vheap_set(hk, hv, pos, size, v, R[v])
    n_faces = F.shape[0]
    n_collapses = 0
    while n_faces > target_faces and size > 0:
        vi = hv[0]
        size = E._vheap_remove(hk, hv, pos, size, vi)
        if stale[vi]:  # a candidate whose star changed: its current R, back into the heap
            stale[vi] = False
            n = E._gather_star(vi, F, face_alive, head, nxt, sbuf)
            K, H, A = E._curvature_at(vi, V, F, sbuf, n, fbuf, ibuf)
            if A > 0.0 and E._curvedness(K, H, no_root) < tau:
                R[vi] = E._curvedness(K, H, no_root)
                size = E._vheap_set(hk, hv, pos, size, vi, R[vi])
            continue
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
            if lazy and pos[w] >= 0:
                stale[w] = True
                continue
            n = E._gather_star(w, F, face_alive, head, nxt, sbuf)
            K, H, A = E._curvature_at(w, V, F, sbuf, n, fbuf, ibuf)
            if pos[w] >= 0:
                size = E._vheap_remove(hk, hv, pos, size, w)
            if A > 0.0 and E._curvedness(K, H, no_root) < tau:
                R[w] = E._curvedness(K, H, no_root)
                size = E._vheap_set(hk, hv, pos, size, w, R[w])
    return face_alive, n_faces, n_collapses, tau


@pytest.mark.parametrize(
    ("seed", "keep", "no_root", "lazy"),
    [
        (1, 0.4, False, True), (2, 0.1, False, True), (3, 0.6, True, True),
        (4, 0.25, False, True), (1, 0.4, False, False), (2, 0.1, False, False),
    ],
)  # fmt: skip
def test_loop_gives_the_naive_reference_mesh_bit_for_bit(seed, keep, no_root, lazy):
    mesh = _blob(seed)
    target = int(mesh.n_faces * keep)
    tol = DEFAULT_TOLERANCES
    ref = prepare(mesh, "curvature", compact_index=True)
    alive, n_ref, coll_ref, tau_ref = _reference_vertex_priority(
        ref.vertices, ref.faces, ref.head, ref.nxt, ref.status, target, no_root,
        tol.max_star, tol.min_quality, lazy,
    )  # fmt: skip
    ref_v, ref_f = _engine.compact(ref.vertices, ref.faces, alive)
    arr = prepare(mesh, "curvature", compact_index=True)
    out = _engine.run_vertex_priority(
        arr.vertices, arr.faces, arr.head, arr.nxt, arr.status, target, no_root,
        tol.max_star, tol.min_quality, lazy,
    )  # fmt: skip
    v, f = _engine.compact(arr.vertices, arr.faces, out[0])
    assert (out[2], out[3], out[4]) == (n_ref, coll_ref, tau_ref)
    assert coll_ref > 0.3 * mesh.n_faces * (1 - keep)  # the loop did collapse
    assert np.array_equal(f, ref_f)
    assert np.array_equal(v, ref_v)


def _textbook_curvatures(V: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Eq. 3 at every vertex, per face and per edge: ``(K, H)`` (NaN where the star is empty).

    ``alpha`` = ``atan2(|e1 x e2|, e1 . e2)`` per face, summed; ``beta`` = ``acos``
    of the dot product of the unit normals of the two faces at an edge (each
    interior edge counted at both of its vertices).
    """
    nv = len(V)
    p0, p1, p2 = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    cr = np.cross(p1 - p0, p2 - p0)
    dbl = np.linalg.norm(cr, axis=1)
    unit = cr / dbl[:, None]
    area = np.zeros(nv)
    asum = np.zeros(nv)
    for k in range(3):
        v, b, c = F[:, k], F[:, (k + 1) % 3], F[:, (k + 2) % 3]
        e1, e2 = V[b] - V[v], V[c] - V[v]
        np.add.at(area, v, 0.5 * dbl)
        ang = np.arctan2(np.linalg.norm(np.cross(e1, e2), axis=1), np.einsum("ij,ij->i", e1, e2))
        np.add.at(asum, v, ang)
    # the two faces at each directed edge (v, b): the face with v -> b and the one with b -> v
    edge_face = {}
    for f, (a, b, c) in enumerate(F):
        for u, w in ((a, b), (b, c), (c, a)):
            edge_face[(int(u), int(w))] = f
    hsum = np.zeros(nv)
    for (u, w), f in edge_face.items():
        g = edge_face[(w, u)]
        beta = np.arccos(np.clip(unit[f] @ unit[g], -1.0, 1.0))
        hsum[u] += np.linalg.norm(V[w] - V[u]) * beta
    third = area / 3.0
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.column_stack([(2 * np.pi - asum) / third, 0.25 * hsum / third])


@pytest.mark.parametrize("seed", [1, 3])
def test_eq3_as_computed_agrees_with_the_textbook_sums(seed):
    mesh = _blob(seed)
    arr = prepare(mesh, "curvature")
    kha = _engine.curvatures(arr.vertices, arr.faces, arr.head, arr.nxt, arr.status, 4096)
    ref = _textbook_curvatures(mesh.vertices, mesh.faces)
    ok = np.isfinite(kha[:, 0])
    assert ok.sum() > 0.9 * len(ok)
    third = kha[ok, 2] / 3.0
    # angle deficit to rounding; sum ||e|| beta to the noise of acos near 1 (~1e-8 rad per edge)
    np.testing.assert_allclose(kha[ok, 0] * third, ref[ok, 0] * third, rtol=0, atol=1e-12)
    np.testing.assert_allclose(kha[ok, 1] * third, ref[ok, 1] * third, rtol=1e-9, atol=1e-7)


@pytest.mark.parametrize("height", [0.0, 0.3, 1.5, 4.0, 30.0])
def test_angle_sum_unwraps_past_full_turns(height):
    """A zigzag fan: ring points alternately above and below, angle sum up to ~7 pi."""
    n = 8
    t = 2 * np.pi * np.arange(n) / n
    ring = np.column_stack([np.cos(t), np.sin(t), height * (-1.0) ** np.arange(n)])
    V = np.vstack([[0.0, 0.0, 0.0], ring, [0.0, 0.0, -100.0]])  # the last: see _closed_fan
    F = np.array([[0, 1 + k, 1 + (k + 1) % n] for k in range(n)], dtype=np.int64)
    K, H, A = _engine._curvature_at(
        0, V, F, np.arange(n), n, np.empty((n, 7)), np.empty((n, 2), dtype=np.int64)
    )
    e1, e2 = V[F[:, 1]], V[F[:, 2]]
    alpha = np.arctan2(np.linalg.norm(np.cross(e1, e2), axis=1), np.einsum("ij,ij->i", e1, e2))
    assert alpha.sum() > (6.5 * np.pi if height == 30.0 else 0.0)
    assert K * A / 3.0 == pytest.approx(2 * np.pi - alpha.sum(), abs=1e-12)
    assert H == pytest.approx(_textbook_curvatures(V, _closed_fan(F, n))[0, 1], rel=1e-9, abs=1e-9)


def _closed_fan(F: np.ndarray, n: int) -> np.ndarray:
    """The fan closed by a second fan around a point far below, so every edge has two faces."""
    cap = np.array([[n + 1, 1 + (k + 1) % n, 1 + k] for k in range(n)], dtype=np.int64)
    return np.vstack([F, cap])


@numba.njit
def _sum_with_prefetch(a, b, idx, hint):  # pragma: no cover - numba
    """Sum of a gather of ``a`` (1-d) and rows of ``b`` (2-d), with or without the hints."""
    s = 0.0
    for k in idx:
        if hint:
            _engine._prefetch(a, k)
            _engine._prefetch(b, 3 * k)
            _engine._prefetch(a, k + 10**9)  # far outside: a hint never faults
        s += a[k % a.shape[0]] + b[k % b.shape[0], 1]
    return s


def test_prefetch_is_only_a_hint():
    rng = np.random.default_rng(5)
    a = rng.integers(-50, 50, 1000).astype(np.int32)
    b = rng.normal(size=(1000, 3))
    idx = rng.integers(0, 1000, 200)
    a0, b0 = a.copy(), b.copy()
    expected = float(np.sum(a[idx]) + np.sum(b[idx, 1]))
    assert _sum_with_prefetch(a, b, idx, True) == pytest.approx(expected, rel=1e-12)
    assert _sum_with_prefetch(a, b, idx, True) == _sum_with_prefetch(a, b, idx, False)
    assert np.array_equal(a, a0) and np.array_equal(b, b0)
