"""Benchmark: mesh simplification at 60 % on marching-cubes meshes up to 1,000,000 faces.

Peers, all measured in the same process on the same mesh (the machine is
shared and noisy, so ratios matter, not absolute times):

* ``curvature`` -- the paper's Algorithm 2 (``simplify_mesh(method="curvature")``);
* ``memoryless`` -- Lindstrom-Turk on the same engine (sizes up to
  ``--memoryless-max-faces`` only: it evaluates ~30 optimal placements per
  collapse);
* ``fast-simplification`` -- ``simplify_mesh(method="qem")`` (Forstmann's QEM);
* ``open3d`` -- ``TriangleMesh.simplify_quadric_decimation`` (Garland-Heckbert QEM).

Each timing is the best of ``--repeats`` runs, peers interleaved. The time
exponent ``t ~ F^k`` is fitted by least squares on log-log over the sizes.
Peak memory of the paper's method on the largest mesh: the process's peak
resident set (``VmHWM``, reset just before the call) during the call.

It also times :func:`tumor3d.geometry.surface.extract_surface` on a 512 x 512 x 300
mask holding a large phantom tumour.

Usage::

    python benchmarks/bench_simplify.py [--repeats 2] [--report reports/benchmarks_simplify.md]
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tumor3d.geometry.surface import extract_surface, is_watertight  # noqa: E402
from tumor3d.phantom import random_tumor_shape  # noqa: E402
from tumor3d.simplify import simplify_mesh  # noqa: E402

#: voxel sizes (mm) of a 60 mm phantom tumour giving about 125k ... 1M faces
SPACINGS_MM = (0.55, 0.39, 0.275, 0.19)
DIAMETER_MM = 60.0


def _mask(shape, z_mm, y_mm, x_mm):
    """Inside-test of a phantom tumour on the grid ``z_mm x y_mm x x_mm``, slab by slab."""
    yy, xx = np.meshgrid(y_mm, x_mm, indexing="ij")
    plane = np.column_stack([xx.ravel(), yy.ravel(), np.zeros(xx.size)])
    mask = np.zeros((len(z_mm), len(y_mm), len(x_mm)), dtype=bool)
    for k, z in enumerate(z_mm):
        plane[:, 2] = z
        mask[k] = shape.contains(plane).reshape(len(y_mm), len(x_mm))
    return mask


def tumour_mesh(spacing_mm: float, seed: int = 7):
    """Marching-cubes surface of a random phantom tumour sampled at ``spacing_mm``."""
    shape = random_tumor_shape(np.random.default_rng(seed), equivalent_diameter_mm=DIAMETER_MM)
    pts = shape.surface_points()
    margin = 0.05 * np.ptp(pts, axis=0) + 2 * spacing_mm  # the samples may miss a bump's top
    lo = pts.min(axis=0) - margin
    hi = pts.max(axis=0) + margin
    axes = [np.arange(lo[k], hi[k], spacing_mm) for k in range(3)]  # x, y, z
    mask = _mask(shape, axes[2], axes[1], axes[0])
    affine = np.diag([spacing_mm, spacing_mm, spacing_mm, 1.0])
    affine[:3, 3] = lo
    return extract_surface(mask, affine)


def _open3d(mesh, target):
    import open3d as o3d

    m = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.array(mesh.vertices)),
        o3d.utility.Vector3iVector(np.array(mesh.faces, dtype=np.int32)),
    )
    return m.simplify_quadric_decimation(target_number_of_triangles=int(target))


def _time(fn, repeats):
    best = np.inf
    out = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t0)
    return best, out


def _peak_rss_mb(mesh) -> tuple[float, float]:
    """Resident set (MB) before, and its peak during, the paper's method on ``mesh``.

    Linux only: the peak (``VmHWM``) is reset through ``/proc/self/clear_refs``
    just before the call, so it measures the whole process during the call.
    """

    def status(key):
        with open("/proc/self/status") as fh:
            return next(float(line.split()[1]) / 1024 for line in fh if line.startswith(key))

    with open("/proc/self/clear_refs", "w") as fh:
        fh.write("5")
    before = status("VmRSS")
    simplify_mesh(mesh, method="curvature", reduction_percent=60.0)
    return before, status("VmHWM")


def _mc_512(repeats):
    shape = random_tumor_shape(np.random.default_rng(3), equivalent_diameter_mm=110.0)
    n_z, n_y, n_x = 300, 512, 512
    spacing = np.array([0.5, 0.45, 0.45])  # (z, y, x) mm
    axes = [(np.arange(n) - n / 2) * s for n, s in zip((n_z, n_y, n_x), spacing, strict=True)]
    mask = _mask(shape, *axes)
    affine = np.diag([spacing[2], spacing[1], spacing[0], 1.0])
    t, mesh = _time(lambda: extract_surface(mask, affine), repeats)
    return t, mesh.n_faces, int(mask.sum())


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--memoryless-max-faces", type=int, default=300_000)
    parser.add_argument("--report", type=Path, default=ROOT / "reports" / "benchmarks_simplify.md")
    args = parser.parse_args()

    # warm-up: numba compilation (cached on disk after the first run)
    small = tumour_mesh(2.0)
    for method in ("curvature", "memoryless", "qem"):
        simplify_mesh(small, method=method, reduction_percent=60.0)

    rows = []
    for spacing in SPACINGS_MM:
        mesh = tumour_mesh(spacing)
        target = int(mesh.n_faces * 0.4)
        peers = {
            "curvature": lambda m=mesh: simplify_mesh(
                m, method="curvature", reduction_percent=60.0
            ),
            "fast-simplification": lambda m=mesh: simplify_mesh(
                m, method="qem", reduction_percent=60.0
            ),
            "open3d": lambda m=mesh, t=target: _open3d(m, t),
        }
        if mesh.n_faces <= args.memoryless_max_faces:
            peers["memoryless"] = lambda m=mesh: simplify_mesh(
                m, method="memoryless", reduction_percent=60.0
            )
        row = {"faces": mesh.n_faces, "vertices": mesh.n_vertices}
        for name, fn in peers.items():
            t, out = _time(fn, args.repeats)
            row[name] = t
            if name in ("curvature", "memoryless", "fast-simplification"):
                row[name + "_watertight"] = is_watertight(out)
        rows.append(row)
        largest_mesh = mesh
        print(row, flush=True)

    faces = np.array([r["faces"] for r in rows], float)
    fits = {}
    for name in ("curvature", "fast-simplification", "open3d", "memoryless"):
        have = [(r["faces"], r[name]) for r in rows if name in r]
        if len(have) >= 3:
            f, t = np.array(have).T
            fits[name] = float(np.polyfit(np.log(f), np.log(t), 1)[0])
    rss_base, rss_run = _peak_rss_mb(largest_mesh)
    t_mc, mc_faces, mc_voxels = _mc_512(args.repeats)

    lines = [
        "# Benchmark: mesh simplification (issue 9)",
        "",
        "Reproduce: `PYTHONPATH=. python benchmarks/bench_simplify.py` "
        f"(repeats={args.repeats}, best of). Machine: {platform.machine()}, "
        f"Python {platform.python_version()}, shared 2-core host (absolute times are noisy; "
        "compare the ratios of peers measured in the same run).",
        "",
        f"Meshes: marching cubes of one random phantom tumour ({DIAMETER_MM:.0f} mm equivalent "
        "diameter) sampled at decreasing voxel sizes; each simplified by P = 60 %.",
        "",
        "| faces | curvature (s) | memoryless (s) | fast-simplification (s) | open3d (s) "
        "| curvature / fast-simpl. | curvature / open3d | curvature watertight "
        "| fast-simpl. watertight |",
        "|---:|---:|---:|---:|---:|---:|---:|:-:|:-:|",
    ]
    for r in rows:
        ms = f"{r['memoryless']:.2f}" if "memoryless" in r else "-"
        lines.append(
            f"| {r['faces']:,} | {r['curvature']:.2f} | {ms} | {r['fast-simplification']:.2f} "
            f"| {r['open3d']:.2f} | {r['curvature'] / r['fast-simplification']:.2f} "
            f"| {r['curvature'] / r['open3d']:.2f} | {r['curvature_watertight']} "
            f"| {r['fast-simplification_watertight']} |"
        )
    lines += [
        "",
        "Fitted time exponent k in t ~ F^k (least squares on log-log over the sizes above; "
        "O(V log V) shows as k slightly above 1):",
        "",
    ]
    lines += [f"- {name}: k = {k:.2f}" for name, k in fits.items()]
    lines += [
        "",
        f"Peak memory, curvature on the {int(faces[-1]):,}-face mesh: the process's resident "
        f"set peaked at {rss_run:.0f} MB during the call ({rss_base:.0f} MB before it: "
        "interpreter, libraries, the mesh and freed buffers the allocator kept).",
        "",
        f"Marching cubes (`extract_surface`) of a 512 x 512 x 300 mask with a "
        f"{mc_voxels:,}-voxel phantom tumour: {t_mc:.2f} s ({mc_faces:,} faces).",
        "",
    ]
    args.report.parent.mkdir(parents=True, exist_ok=True)
    args.report.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
