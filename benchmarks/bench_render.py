"""Benchmark: 8 views (6 anatomical + 2 cut-aways) of a 100,000-face tumour in a brain.

Target of issue 10: all views of a patient in one renderer start, 8 views of a
100,000-face mesh with the brain in at most 3 s at 640x480.

Scene: a marching-cubes ball of ~100,000 faces (radius 20.8 mm, 0.4 mm voxels)
inside a marching-cubes ellipsoid brain of ~170,000 faces (70 x 72 x 60 mm,
1 mm voxels), off-centre. Peers, in one process, after a warm-up (numba
compilation; Open3D's Mesa shader cache):

* ``numpy, 8 views``: :func:`tumor3d.visual.render.render_views` with the default
  numba z-buffer renderer (median of ``--repeats``);
* ``numpy, 1 view``: the same call with one anatomical view and no cut-away:
  the fixed cost (scene set-up, normals, clipping) against the per-view cost;
* ``numpy, 8 views + 24 turntable frames``: the pipeline's default set of
  frames (the render stage's cost per patient);
* ``same, per-frame numpy buffers``: the same 32 frames composed as before
  (a new float64 frame filled by numpy broadcasting, new z-buffer and
  fragment buffers for every layer, ``rint(255 img).astype(uint8)``), the
  baseline of the renderer's frame kernels (``_clear``, ``_to_uint8``,
  buffers reused across frames); the same rasteriser and shader, so the
  same pixels (checked);
* ``open3d, 8 views``: the same scene with Open3D's Filament (one child
  process, one renderer start), once (it is slow on llvmpipe); skip with
  ``--no-open3d``.

Reported: seconds and ratios against ``numpy, 8 views``; the machine's load
average, since the machine is shared.

Usage::

    python benchmarks/bench_render.py [--repeats 3] [--no-open3d]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import tumor3d.visual.render.views as views_mod  # noqa: E402
from tumor3d.geometry.surface import extract_surface  # noqa: E402
from tumor3d.visual.render import render_views  # noqa: E402
from tumor3d.visual.render.raster import _raster, _shade  # noqa: E402


def _render_per_frame_buffers(scene, lighting):
    """The frame composition before the frame kernels (the baseline peer)."""
    w, h = scene["size"]
    geoms = scene["geoms"]
    out = np.empty((len(scene["cameras"]), h, w, 3), dtype=np.uint8)
    k_a, k_d, k_s, s = (float(x) for x in lighting)

    def layer(g, cam, zbuf, img):
        p = cam.project(g["vertices"])
        fid = np.full((h, w), -1, dtype=np.int64)
        b1 = np.zeros((h, w))
        b2 = np.zeros((h, w))
        faces = np.ascontiguousarray(g["faces"], dtype=np.int64)
        _raster(np.ascontiguousarray(p[:, 0]), np.ascontiguousarray(p[:, 1]),
                np.ascontiguousarray(p[:, 2]), faces, w, h, zbuf, fid, b1, b2, True)  # fmt: skip
        _shade(img, fid, b1, b2, faces, np.ascontiguousarray(g["normals"], dtype=np.float64),
               np.ascontiguousarray(g["color"], dtype=np.float64),
               np.ascontiguousarray(-cam.forward, dtype=np.float64), k_a, k_d, k_s, s,
               float(g["opacity"]))  # fmt: skip

    for k, (cam, vis) in enumerate(zip(scene["cameras"], scene["visible"], strict=True)):
        img = np.empty((h, w, 3))
        img[:] = scene["background"]
        zbuf = np.full((h, w), np.inf)
        for g in (geoms[i] for i in vis if geoms[i]["opacity"] >= 1.0):
            layer(g, cam, zbuf, img)
        for g in (geoms[i] for i in vis if geoms[i]["opacity"] < 1.0):
            layer(g, cam, zbuf.copy(), img)
        out[k] = np.rint(img * 255.0).astype(np.uint8)
    return out


def scene():
    size = 150
    c = (size - 1) / 2
    z, y, x = np.ogrid[:size, :size, :size]
    brain_mask = ((x - c) / 70) ** 2 + ((y - c) / 72) ** 2 + ((z - c) / 60) ** 2 <= 1
    aff = np.eye(4)
    aff[:3, 3] = -c
    brain = extract_surface(brain_mask, aff)
    s2 = 120
    c2 = (s2 - 1) / 2
    z, y, x = np.ogrid[:s2, :s2, :s2]
    tumor_mask = (x - c2) ** 2 + (y - c2) ** 2 + (z - c2) ** 2 <= 52**2
    aff2 = np.diag([0.4, 0.4, 0.4, 1.0])
    aff2[:3, 3] = -c2 * 0.4 + np.array([20.0, 10.0, 5.0])
    return extract_surface(tumor_mask, aff2), brain


def timed(fn):
    t0 = time.perf_counter()
    out = fn()
    return time.perf_counter() - t0, out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-open3d", action="store_true")
    args = parser.parse_args()

    tumor, brain = scene()
    print(
        f"tumour {tumor.n_faces} faces, brain {brain.n_faces} faces, 640x480, "
        f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs"
    )
    common = {"brain": brain, "width": 640, "height": 480, "turntable_frames": 0}

    def eight():
        return render_views(tumor, **common)

    def one():
        return render_views(tumor, views=("anterior",), cutaways=(), **common)

    def thirty_two():
        return render_views(tumor, **{**common, "turntable_frames": 24})

    def thirty_two_before():
        real = views_mod._render_numpy
        views_mod._render_numpy = _render_per_frame_buffers
        try:
            return render_views(tumor, **{**common, "turntable_frames": 24})
        finally:
            views_mod._render_numpy = real

    eight()  # warm-up: numba compilation (cached on disk after the first run)
    one()
    now, before = thirty_two(), thirty_two_before()
    same = all(np.array_equal(now.images[k], before.images[k]) for k in now.images) and all(
        np.array_equal(a, b) for a, b in zip(now.turntable, before.turntable, strict=True)
    )
    assert same, "the frame kernels changed a pixel"
    t8, t1, t32, t32b = [], [], [], []
    for _ in range(args.repeats):
        t8.append(timed(eight)[0])
        t1.append(timed(one)[0])
        t32.append(timed(thirty_two)[0])
        t32b.append(timed(thirty_two_before)[0])
    rows = [
        ("numpy, 8 views", statistics.median(t8)),
        ("numpy, 1 view", statistics.median(t1)),
        ("numpy, 8 views + 24 turntable frames", statistics.median(t32)),
        ("same, per-frame numpy buffers", statistics.median(t32b)),
    ]
    if not args.no_open3d:
        t, res = timed(lambda: render_views(tumor, renderer="open3d", **common))
        assert res.info["renderer"] == "open3d"
        rows.append(("open3d, 8 views", t))
    ref = rows[0][1]
    print(f"{'peer':<38}{'seconds':>9}{'ratio':>9}")
    for name, t in rows:
        print(f"{name:<38}{t:>9.2f}{t / ref:>9.2f}")
    print(
        f"frame kernels: 32 frames {rows[2][1]:.2f} s against {rows[3][1]:.2f} s with "
        f"per-frame numpy buffers ({rows[3][1] / rows[2][1]:.2f}x), same pixels"
    )
    verdict = "meets" if ref <= 3.0 else "misses"
    print(
        f"8 views with the brain: {ref:.2f} s ({verdict} the 3 s target); "
        f"per extra view {(ref - rows[1][1]) / 7:.3f} s"
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
