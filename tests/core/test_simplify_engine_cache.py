"""The collapse engine's numba cache follows every engine file (issue 32 item 4).

The engine is split over several files whose kernels inline one another and
are ``njit(cache=True)``; numba checks a cached kernel against its own file
only. :mod:`tumor3d.simplify._jit` gives the kernels of all engine files one
source stamp, so an edit to a callee's file (a heap function inlined into
``run_vertex_priority``, say) recompiles its callers instead of loading
stale machine code.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numba
import pytest

from tumor3d.simplify import _engine, _jit

PACKAGE = Path(_jit.__file__).parent


def test_every_file_with_cached_kernels_is_an_engine_module():
    cached = {p.name for p in PACKAGE.glob("*.py") if "cache=True" in p.read_text()}
    assert cached <= set(_jit.ENGINE_MODULES)
    assert all((PACKAGE / name).is_file() for name in _jit.ENGINE_MODULES)


def test_the_stamp_changes_with_any_engine_file(tmp_path):
    for name in _jit.ENGINE_MODULES:
        shutil.copy2(PACKAGE / name, tmp_path / name)
    base = _jit.group_stamp(str(tmp_path))
    assert base == _jit.group_stamp(str(PACKAGE))  # content, not place or time
    for name in _jit.ENGINE_MODULES:
        text = (tmp_path / name).read_text()
        (tmp_path / name).write_text(text + "\n# edited\n")
        assert _jit.group_stamp(str(tmp_path)) != base, name
        (tmp_path / name).write_text(text)
        assert _jit.group_stamp(str(tmp_path)) == base


@pytest.mark.parametrize(
    "kernel",
    [_engine.run_vertex_priority, _engine.run_edge_priority, _engine.build_corner_lists,
     _engine.curvatures, _engine.compact, _engine.vertex_status, _engine._check_star_geometry],
)  # fmt: skip
def test_engine_kernels_are_cached_under_the_group_stamp(kernel):
    assert isinstance(kernel, numba.core.registry.CPUDispatcher)
    locator = kernel._cache._impl.locator
    assert type(locator).__name__ == "_GroupStampLocator"
    assert locator.get_source_stamp() == _jit.group_stamp()
    # the cache stays where numba puts it: beside the kernel's own source (or NUMBA_CACHE_DIR)
    assert locator.get_cache_path() == locator._inner.get_cache_path()
