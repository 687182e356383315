"""The curvature scheduler's speed-ups change no result (issues 30 and 32).

* the indexed vertex heap pops in the order of ``(key, v)`` under inserts,
  key changes (ties included) and removals, like the lazy-deletion heap it
  replaced;
* int32 and int64 index arrays give the same mesh.

The meshes themselves were compared bit for bit with the former kernel
(lazy-deletion heap, int64) when the change was made: the 1 M-face benchmark
mesh at P = 60 % and a 237 k-face one at P = 60 / 90 % (tau once and
refresh) and 40 % (no_root), identical (``reports/benchmarks.md``).
"""

from __future__ import annotations

import numpy as np
import pytest

from tumor3d.mesh import Mesh
from tumor3d.simplify import _engine
from tumor3d.simplify._prepare import DEFAULT_TOLERANCES, prepare
from tumor3d.surface import extract_surface


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
