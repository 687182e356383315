"""tumor3d.warmup: after it, a first patient compiles no numba kernel (issue 32 item 1)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.slow

# A first patient in a new process, every stage of the pipeline (the stage adapters, as a
# flow runs them, without Prefect): how many numba compilations it starts.
_FIRST_PATIENT = """
import sys
from numba.core import event
from storage.phantom_io import write_phantom_patient
from tumor3d.phantom import make_phantom_patient

patient = make_phantom_patient(5, n_slices=12, matrix_size=(112, 112), patient_id="warm5")
row = write_phantom_patient(patient, sys.argv[1])
from flows.patient import run_stages_direct

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


def test_after_the_warm_up_a_first_patient_compiles_nothing(tmp_path):
    cache = tmp_path / "numba-cache"  # a new installation's empty cache
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    warm = subprocess.run(
        [sys.executable, "-m", "tumor3d.warmup"], env=env, capture_output=True, text=True,
        timeout=900,
    )  # fmt: skip
    assert warm.returncode == 0 and "numba kernels compiled and cached" in warm.stdout
    assert any(cache.rglob("*.nbi")), "numba wrote no cache index"
    compiled, names = _first_patient(tmp_path, cache)
    assert compiled == 0, f"compiled after the warm-up: {names}"


def test_without_the_warm_up_the_first_patient_compiles(tmp_path):
    """The measure above is not vacuous: an empty cache does compile the kernels."""
    compiled, names = _first_patient(tmp_path, tmp_path / "empty-cache")
    assert compiled > 0 and "tumor3d.simplify._engine." in names, names
