"""numba settings shared by the collapse engine's modules, and the cache hint.

The engine (:mod:`tumor3d.simplify._engine`) is split by concept over
:data:`ENGINE_MODULES`; its kernels call one another across those files and
are ``numba.njit(cache=True)``. numba decides whether a cached kernel is
still valid from the source of the kernel's own file only, so a change to
a callee in another file (an inlined heap or curvature function, say) would
leave the caller's cached machine code stale. Importing this module (every
engine module does, first) makes the cache of every kernel of those files
depend on all of them: :class:`_GroupStampLocator` gives them one source
stamp, the digest of every engine file, and leaves where numba puts the
cache (``__pycache__`` beside the source, or ``NUMBA_CACHE_DIR``) as it is.
"""

from __future__ import annotations

import functools
import hashlib
import os

from llvmlite import ir
from numba.core import caching, cgutils, types
from numba.extending import intrinsic

#: the files of the collapse engine (this package); their kernels share one cache stamp
ENGINE_MODULES = (
    "_jit.py", "_topology.py", "_heap.py", "_curvature_kernels.py", "_collapse.py",
    "_edge_cost.py", "_engine.py",
)  # fmt: skip
_HERE = os.path.dirname(os.path.abspath(__file__))


@functools.cache
def _file_digest(path: str, mtime_ns: int, size: int) -> bytes:
    """sha256 of a file (memoised on its modification time and size, as numba does)."""
    with open(path, "rb") as fh:
        return hashlib.sha256(fh.read()).digest()


def group_stamp(directory: str = _HERE) -> bytes:
    """The engine's cache stamp: one digest of its :data:`ENGINE_MODULES` files in ``directory``."""
    digest = hashlib.sha256()
    for name in ENGINE_MODULES:
        path = os.path.join(directory, name)
        st = os.stat(path)
        digest.update(name.encode())
        digest.update(_file_digest(path, st.st_mtime_ns, st.st_size))
    return digest.digest()


class _GroupStampLocator:
    """numba's own cache locator for an engine file, with :func:`group_stamp` as source stamp."""

    def __init__(self, inner: object) -> None:
        self._inner = inner

    def __getattr__(self, name: str) -> object:
        return getattr(self._inner, name)

    def get_source_stamp(self) -> bytes:
        """The stamp numba stores in (and checks against) the cache index."""
        return group_stamp()

    @classmethod
    def from_function(cls, py_func, py_file):  # type: ignore[no-untyped-def]
        """Wrap the locator numba would choose, for a kernel of an engine file only."""
        path = os.path.abspath(py_file)
        if os.path.dirname(path) != _HERE or os.path.basename(path) not in ENGINE_MODULES:
            return None
        for other in _CACHE_IMPL._locator_classes:
            if other is not cls:
                inner = other.from_function(py_func, py_file)
                if inner is not None:
                    return cls(inner)
        return None


_CACHE_IMPL = getattr(caching, "CacheImpl", None) or caching._CacheImpl
if not any(c.__name__ == "_GroupStampLocator" for c in _CACHE_IMPL._locator_classes):
    _CACHE_IMPL._locator_classes.insert(0, _GroupStampLocator)

#: LLVM fast-math flags without "no NaN / no inf" (the engine uses inf as a sentinel)
_FASTMATH: set[str] = set()


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
