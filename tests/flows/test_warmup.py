"""tumor3d.warmup: after it, a first patient compiles no numba kernel (issue 32 item 1)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow

# A first patient in a new process, every stage of the pipeline (the stage adapters, as a
# flow runs them, without Prefect): how many numba compilations it starts.
_FIRST_PATIENT = """
import sys
from numba.core import event
from tumor3d.storage.phantom_io import write_phantom_patient
from tumor3d.phantom import make_phantom_patient

patient = make_phantom_patient(5, n_slices=12, matrix_size=(112, 112), patient_id="warm5")
row = write_phantom_patient(patient, sys.argv[1])
from tumor3d.flows.patient import run_stages_direct

with event.install_recorder("numba:compile") as rec:
    runner = run_stages_direct(row.image, sys.argv[2], patient_id="warm5", modality="t2")
assert runner.outputs["simplify-mesh"].values["faces"] > 0
starts = [e.data for _, e in rec.buffer if e.is_start]
names = sorted({d["dispatcher"].py_func.__module__ + "." + d["dispatcher"].py_func.__name__
                for d in starts})
print(len(starts), ",".join(names))
"""


def _first_patient(tmp_path, cache_dir):
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache_dir)}
    out = subprocess.run(
        [sys.executable, "-c", _FIRST_PATIENT, str(tmp_path / "in"), str(tmp_path / "store")],
        env=env, capture_output=True, text=True, timeout=900,
    )  # fmt: skip
    assert out.returncode == 0, out.stderr[-2000:]
    count, _, names = out.stdout.strip().partition(" ")
    return int(count), names


@pytest.fixture(scope="module")
def warm_cache(tmp_path_factory):
    """A new installation's empty numba cache, after ``python -m tumor3d.warmup``."""
    cache = tmp_path_factory.mktemp("numba-cache")
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    warm = subprocess.run(
        [sys.executable, "-m", "tumor3d.warmup"], env=env, capture_output=True, text=True,
        timeout=900,
    )  # fmt: skip
    assert warm.returncode == 0 and "numba kernels compiled and cached" in warm.stdout
    assert any(cache.rglob("*.nbi")), "numba wrote no cache index"
    return cache


def test_after_the_warm_up_a_first_patient_compiles_nothing(tmp_path, warm_cache):
    cache = tmp_path / "numba-cache"
    shutil.copytree(warm_cache, cache)
    compiled, names = _first_patient(tmp_path, cache)
    assert compiled == 0, f"compiled after the warm-up: {names}"


def test_a_kernel_missing_from_the_warm_cache_is_compiled_by_the_first_patient(
    tmp_path, warm_cache
):
    """The measure above is not vacuous: the same first patient, on the warmed cache less
    one kernel's entries (the simplifier's, called from Python on every run), compiles
    that kernel and the recorder counts it. (A full compile on an empty cache proves no
    more and costs a second warm-up's time.)"""
    cache = tmp_path / "numba-cache"
    shutil.copytree(warm_cache, cache)
    dropped = list(cache.rglob("_engine.build_corner_lists-*.nb*"))
    assert any(f.suffix == ".nbi" for f in dropped), sorted(p.name for p in cache.rglob("*"))
    for f in dropped:
        f.unlink()
    compiled, names = _first_patient(tmp_path, cache)
    assert compiled > 0 and "tumor3d.simplify._engine.build_corner_lists" in names, names
