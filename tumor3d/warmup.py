"""Compile every numba kernel once, ahead of the first patient: ``python -m tumor3d.warmup``.

The kernels (the simplifier's collapse engine in :mod:`tumor3d.simplify`,
the exact distance transforms of :mod:`tumor3d.geometry.distance`, the tree walk of
the learned segmentation (:mod:`tumor3d.learned.forest`), the z-buffer
renderer of :mod:`tumor3d.visual.render.raster` and the phantom rasteriser of
:mod:`tumor3d.phantom.raster`) are ``numba.njit(cache=True)``: compiled
on their first call in a process and written to numba's cache (by default
``__pycache__`` beside their source; ``NUMBA_CACHE_DIR`` elsewhere), which
every later process loads in milliseconds. Without a warm-up the first
``tumor3d demo`` of a new installation spent 18-29 s of ``simplify-mesh``
compiling the collapse engine (2026-12-04; since each kernel compiles once, a
first patient's kernels take about 14 s: ``reports/benchmarks.md``).

:func:`warm_up` calls them through the same public functions, with the
same argument types, as a run does: a small phantom patient reconstructed
by :func:`tumor3d.api.reconstruct_scan` (preprocessing to volumes, the
default configuration), every simplification method, and the renderer.
``make setup`` runs it once after installing; it takes about as long as
the compilation it saves, and then nothing on the next call.

The function computes on arrays only; numba itself writes its cache.
"""

from __future__ import annotations

import sys
import time

__all__ = ["warm_up"]


def warm_up() -> dict[str, float]:
    """Call every numba kernel once with a run's argument types; returns seconds per step."""
    seconds: dict[str, float] = {}

    def step(name: str, fn):  # type: ignore[no-untyped-def]
        t0 = time.perf_counter()
        out = fn()
        seconds[name] = time.perf_counter() - t0
        return out

    from tumor3d.api import reconstruct_scan
    from tumor3d.config import PipelineConfig
    from tumor3d.phantom import make_phantom_patient
    from tumor3d.simplify import METHODS, simplify_mesh
    from tumor3d.visual.render import render_views

    patient = step(
        "phantom (raster)",
        lambda: make_phantom_patient(0, n_slices=10, matrix_size=(96, 96), patient_id="warmup"),
    )
    result = step("pipeline (distance, simplify)", lambda: reconstruct_scan(patient.scan))
    flair = make_phantom_patient(
        0, n_slices=10, matrix_size=(96, 96), patient_id="warmup", modality="flair"
    )
    step("learned segmentation (forest)", lambda: reconstruct_scan(flair.scan))
    mesh = result.mesh
    for method in METHODS:
        step(
            f"simplify {method}",
            lambda m=method: simplify_mesh(mesh, method=m, reduction_percent=60.0),
        )
    cfg = PipelineConfig().render.model_dump()
    cfg.update(width=64, height=64, views=("anterior",), cutaways=("axial",), turntable_frames=1)
    cfg["renderer"] = "numpy"
    step("render (z-buffer)", lambda: render_views(mesh, brain=mesh, **cfg))
    return seconds


def main() -> int:  # pragma: no cover - console entry
    """Warm up and say how long each step took."""
    t0 = time.perf_counter()
    seconds = warm_up()
    steps = ", ".join(f"{k} {v:.1f} s" for k, v in seconds.items())
    total = time.perf_counter() - t0
    print(f"tumor3d: numba kernels compiled and cached in {total:.1f} s ({steps})")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
