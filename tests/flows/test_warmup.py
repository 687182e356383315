"""tumor3d.warmup: after it, a first patient compiles no numba kernel (issue 32 item 1).

The warm-up runs as a new installation runs it, into an empty numba cache, except for
the kernels a first patient never calls (the phantom's rasteriser: the patient's scan is
written beforehand; the curvature simplifier and the learned forest: not in a default T2
run): their entries are copied in from the checkout's own cache (filled by ``make setup``)
so that the warm-up loads them instead of spending a minute compiling them, and are taken
out again before the first patient runs. The first patient therefore sees only what the
warm-up itself wrote; had it needed a seeded kernel, it would compile it and fail.
"""

from __future__ import annotations

import filecmp
import json
import os
import shutil
import subprocess
import sys
from collections import Counter
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

# module -> kernels (qualified names; "*" = all) that a first default T2 patient never calls
NOT_CALLED_BY_A_FIRST_PATIENT = {
    "tumor3d.phantom.raster": ("*",),
    "tumor3d.simplify._engine": ("run_vertex_priority", "curvatures"),
    "tumor3d.learned.forest": ("*",),
}

# A first patient in a new process, every stage of the pipeline (the stage adapters, as a
# flow runs them, without Prefect): the numba compilations it starts, as JSON: [qualified
# name, argument types without literal values and read-only flags] of each compilation
# started from Python (not inside another one's: numba's own overloads compile there).
_FIRST_PATIENT = """
import json, sys
from numba.core import event, types
from tumor3d.flows.patient import run_stages_direct

def plain(t):
    t = types.unliteral(t)
    return t.copy(readonly=False) if isinstance(t, types.Array) else t

with event.install_recorder("numba:compile") as rec:
    runner = run_stages_direct(sys.argv[1], sys.argv[2], patient_id="warm5", modality="t2")
assert runner.outputs["simplify-mesh"].values["faces"] > 0
outer, depth = [], 0
for _, e in rec.buffer:
    if e.is_start:
        if depth == 0:
            f = e.data["dispatcher"].py_func
            outer.append([f.__module__ + "." + f.__qualname__,
                          [repr(plain(a)) for a in e.data["args"]]])
        depth += 1
    elif e.is_end:
        depth -= 1
print(json.dumps(outer))
"""


@pytest.fixture(scope="module")
def first_scan(tmp_path_factory) -> Path:
    """The first patient's scan (a small phantom)."""
    from tumor3d.phantom import make_phantom_patient
    from tumor3d.storage.phantom_io import write_phantom_patient

    patient = make_phantom_patient(5, n_slices=12, matrix_size=(112, 112), patient_id="warm5")
    return write_phantom_patient(patient, tmp_path_factory.mktemp("in")).image


def _first_patient(tmp_path, cache_dir, scan):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir)}
    out = subprocess.run(
        [sys.executable, "-c", _FIRST_PATIENT, str(scan), str(tmp_path / "store")],
        env=env, capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    return [(name, tuple(args)) for name, args in json.loads(out.stdout.strip().splitlines()[-1])]


def _seed(cache: Path) -> dict[Path, Path]:
    """Copy the checkout's cache entries of the kernels above into ``cache``, where numba
    looks under ``NUMBA_CACHE_DIR``; returns copy -> source (absent entries: none)."""
    import importlib

    from numba.core.caching import _CacheLocator

    seeded = {}
    for module, kernels in NOT_CALLED_BY_A_FIRST_PATIENT.items():
        py_file = Path(importlib.import_module(module).__file__).resolve()
        stem = py_file.stem
        dest = cache / _CacheLocator.get_suitable_cache_subpath(str(py_file))
        for kernel in kernels:
            pattern = f"{stem}.*.nb[ic]" if kernel == "*" else f"{stem}.{kernel}-*.nb[ic]"
            for src in (py_file.parent / "__pycache__").glob(pattern):
                dest.mkdir(parents=True, exist_ok=True)
                shutil.copy2(src, dest / src.name)
                seeded[dest / src.name] = src
    return seeded


# ``python -m tumor3d.warmup``, then one line "compiled: " + JSON of what it compiled:
# [qualified name, argument types, the same without literal values and read-only flags]
# per compilation
_WARM_UP = """
import json
from numba.core import event, types
from tumor3d.warmup import main

def plain(t):
    t = types.unliteral(t)
    return t.copy(readonly=False) if isinstance(t, types.Array) else t

with event.install_recorder("numba:compile") as rec:
    main()
compiled = [[f.__module__ + "." + f.__qualname__, [repr(a) for a in d["args"]],
             [repr(plain(a)) for a in d["args"]]]
            for d in (e.data for _, e in rec.buffer if e.is_start)
            for f in [d["dispatcher"].py_func]]
print("compiled:", json.dumps(compiled))
"""


@pytest.fixture(scope="module")
def warm_up_run(tmp_path_factory):
    """A new installation's numba cache after ``python -m tumor3d.warmup`` (see above),
    and what the warm-up compiled on the way (qualified name, argument types, the same
    types without literal values and read-only flags)."""
    cache = tmp_path_factory.mktemp("numba-cache")
    seeded = _seed(cache)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    warm = subprocess.run(
        [sys.executable, "-c", _WARM_UP], env=env, capture_output=True, text=True,
        timeout=900,
    )  # fmt: skip
    assert warm.returncode == 0, warm.stderr[-2000:]
    assert "numba kernels compiled and cached" in warm.stdout, warm.stdout[-2000:]
    lines = [ln for ln in warm.stdout.splitlines() if ln.startswith("compiled: ")]
    assert len(lines) == 1, warm.stdout[-2000:]
    compiled = lines[0].removeprefix("compiled: ")
    # the seeded entries go again (an index the warm-up rewrote is the warm-up's own)
    for copy, src in seeded.items():
        if filecmp.cmp(copy, src, shallow=False):
            copy.unlink()
    assert any(cache.rglob("*.nbi")), "numba wrote no cache index"
    return cache, json.loads(compiled)


def test_the_warm_up_compiles_a_kernel_once_per_argument_types(warm_up_run):
    """Every new installation waits for these compilations: no kernel the warm-up compiles
    (the seeded ones above load from the cache) is compiled twice for argument types that
    differ only in a literal value or an array's read-only flag (a ``0`` passed as a
    constant compiled a second copy of the edge simplifier's heap and all it calls, ~5 s;
    the renderer compiled twice, for a mesh's read-only faces and a cut-away's writable
    ones)."""
    _, compiled = warm_up_run
    ours = {(name, tuple(args), tuple(plain)) for name, args, plain in compiled
            if name.startswith("tumor3d.")}  # fmt: skip
    assert len(ours) > 20  # the edge simplifier, the renderer, the distances (not seeded)
    copies = Counter((name, plain) for name, _, plain in ours)
    twice = sorted((name, args) for name, args, plain in ours if copies[name, plain] > 1)
    assert not twice, twice


def test_after_the_warm_up_a_first_patient_compiles_only_a_kernel_taken_out_of_it(
    tmp_path, warm_up_run, first_scan
):
    """A first patient on the warm-up's cache compiles nothing the warm-up compiled.

    One kernel's entries (the simplifier's ``build_corner_lists``, called from Python on
    every run) are taken out of that cache first, so that the measure is not vacuous: the
    patient must compile that kernel once, for argument types the warm-up compiled it
    for, the recorder must count it, and nothing else may be compiled from Python (a
    kernel the warm-up missed would be; numba's own overloads compiled inside that
    kernel's compilation are its part). One first patient checks both, not two (each is a
    new process: imports and a whole patient).
    """
    warm_cache, warm_compiled = warm_up_run
    kernel = "tumor3d.simplify._engine.build_corner_lists"
    cache = tmp_path / "numba-cache"
    shutil.copytree(warm_cache, cache)
    dropped = list(cache.rglob("_engine.build_corner_lists-*.nb*"))
    assert any(f.suffix == ".nbi" for f in dropped), sorted(p.name for p in cache.rglob("*"))
    for f in dropped:
        f.unlink()
    compiled = _first_patient(tmp_path, cache, first_scan)
    assert [name for name, _ in compiled] == [kernel], f"compiled after the warm-up: {compiled}"
    warm_types = {tuple(plain) for name, _, plain in warm_compiled if name == kernel}
    assert compiled[0][1] in warm_types, (compiled[0][1], warm_types)
