"""The engine's priority queues (numba kernels).

* a binary min-heap of ``(key, a, b, c, d)`` entries ordered by
  ``(key, a, b)``, with lazy deletion by the caller (the edge scheduler);
* an indexed binary min-heap of vertices on ``(key, v)``, one entry per
  vertex, with its position array (the vertex scheduler of Algorithm 2).

Written for compile time as well as run time (every new installation compiles them,
``python -m tumor3d.warmup``): a constant ``0`` passed to a kernel is typed
``Literal[int](0)`` and compiles a second copy of the kernel and of everything it
calls, so callers pass ``np.int64(0)``; arrays are copied element by element, since
a slice copy compiles numba's shape-mismatch message (string formatting, about 2 s).
"""

from __future__ import annotations

import numba
import numpy as np

from tumor3d.simplify._jit import _FASTMATH


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
        for i in range(size):  # not a slice copy (module docstring)
            nk[i] = keys[i]
            for c in range(pay.shape[1]):
                npay[i, c] = pay[i, c]
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
    top = np.int64(0)  # not the literal 0 (module docstring)
    _swap(keys, pay, top, size)
    _sift_down(keys, pay, size, top)
    return size


@numba.njit(cache=True, fastmath=_FASTMATH)
def _heapify(keys, pay, size):  # pragma: no cover - numba
    for pos in range(size // 2 - 1, -1, -1):
        _sift_down(keys, pay, size, pos)


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
