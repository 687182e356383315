"""The learned model's parallel prediction prints nothing, even beside Open3D's TBB.

numba picks its parallel layer when a parallel function first runs; it tried
TBB first and, with the older TBB that Open3D loads into the process (the
render stage imports it), printed a NumbaWarning on stderr (an error in the
test suite) before falling back. :mod:`tumor3d.learned.forest` puts OpenMP
first. Checked in a fresh interpreter with warnings as errors, Open3D
imported first, the kernel loaded from numba's cache or compiled.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

SCRIPT = """
import open3d  # loads its TBB first, as a pipeline process does after a render
import numpy as np
import numba
from tumor3d.learned.shipped import shipped_model
from tumor3d.learned.forest import predict_proba

m = shipped_model("flair")
p = predict_proba(m, np.zeros((64, m.n_features), np.float32))
assert p.shape == (64,) and np.all((p >= 0) & (p <= 1))
print(numba.threading_layer())
"""


def test_prediction_beside_open3d_warns_nothing():
    pytest.importorskip("open3d")
    env = {k: v for k, v in os.environ.items() if not k.startswith("NUMBA_THREADING_LAYER")}
    res = subprocess.run(
        [sys.executable, "-W", "error", "-c", SCRIPT], capture_output=True, text=True,
        env={**env, "PYTHONPATH": str(ROOT)}, cwd=str(ROOT), timeout=300,
    )  # fmt: skip
    assert res.returncode == 0, res.stderr[-2000:]
    assert res.stderr.strip() == "", res.stderr[-2000:]
    assert res.stdout.strip() in ("omp", "tbb", "workqueue")
