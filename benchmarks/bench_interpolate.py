"""Speed of inter-slice interpolation: 31 masks of 240x240 to 151 slices, against ITK.

The input is a drifting lobed phantom tumour on a 155 x 240 x 240 grid of 1 mm
voxels, every 5th slice kept (31 slices, 4 inserted per gap: 151 fine slices).
ITK's MorphologicalContourInterpolator fills the same 31 slices on the 155-slice
grid. Times are the best of several runs after a warm-up (numba JIT, ITK's lazy
module loading); the figure that matters is the ratio to ITK in the same process.

    PYTHONPATH=. python benchmarks/bench_interpolate.py
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

from tumor3d.evaluation.interpolation import (
    drifting_tumour_phantom,
    itk_available,
    itk_contour_interpolate,
)
from tumor3d.geometry.interpolate import interpolate_stack

CONFIGS = {
    "default (shape-edt, matched, taper)": {
        "method": "shape-edt",
        "parts": "matched",
        "end_caps": "taper",
    },
    "SE-EDT parts (enhanced-edt, matched, taper)": {
        "method": "enhanced-edt",
        "parts": "matched",
        "end_caps": "taper",
    },
    "SE literal (enhanced, whole, none)": {
        "method": "enhanced",
        "parts": "whole",
        "end_caps": "none",
    },
    "SO (shape, whole, none)": {"method": "shape", "parts": "whole", "end_caps": "none"},
}


def _best_of(fn, repeats: int) -> float:
    fn()  # warm-up
    best = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def benchmark_markdown(repeats: int = 5) -> str:
    label = drifting_tumour_phantom(
        0, shape=(155, 240, 240), drift_mm_per_mm=(0.3, 0.4), axes_mm=(20.0, 40.0)
    )
    thick = label[::5]
    sparse = np.zeros_like(label)
    sparse[::5] = thick
    times = {
        name: _best_of(lambda kw=kw: interpolate_stack(thick, slices_between=4, **kw), repeats)
        for name, kw in CONFIGS.items()
    }
    t_itk = _best_of(lambda: itk_contour_interpolate(sparse), repeats) if itk_available() else None
    n_fine = (len(thick) - 1) * 5 + 1
    lines = [
        "## Speed",
        "",
        f"`PYTHONPATH=. python benchmarks/bench_interpolate.py`: {len(thick)} masks of 240x240 "
        f"({int(thick.any(axis=(1, 2)).sum())} with tumour) to {n_fine} slices, best of "
        f"{repeats} after a warm-up, this machine (2 shared cores). Target: <= 0.1 s.",
        "",
        "| method | time (s) | ratio to ITK |",
        "|---|---:|---:|",
    ]
    for name, t in times.items():
        ratio = f"{t / t_itk:.2f}" if t_itk else "n/a"
        lines.append(f"| {name} | {t:.4f} | {ratio} |")
    if t_itk is not None:
        lines.append(f"| ITK MorphologicalContourInterpolator (155 slices) | {t_itk:.4f} | 1.00 |")
    else:
        lines.append("| ITK | not installed (`pip install 'tumor3d[peers]'`) | |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    print(benchmark_markdown())
    sys.stdout.flush()
    os._exit(0)  # see interpolation_eval.py: ITK's teardown can crash at exit
