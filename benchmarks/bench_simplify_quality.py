"""Figure 10's errors of the curvature method with step 6 lazy and eager (issues 30 and 32).

``simplify_curvature(ring_update="lazy")`` (the default: a candidate whose
star changed is re-evaluated when it reaches the top of the heap) against
``ring_update="eager"`` (the paper's order: every ring vertex re-keyed after
each collapse), on the cases of ``benchmarks/simplification_eval.py`` (three
phantoms, the three BraTS labels when ``TUMOR3D_DATA_DIR`` has them) at
P = 20 ... 90 %, with the measures of
:mod:`tumor3d.evaluation.simplification` (Eq. 11 SHD, point-to-surface
Hausdorff and mean distance on 20,000 samples, volume change, watertight).
Prints one row per case and P and the means over the rows where both reach
the same face count.

Usage::

    TUMOR3D_DATA_DIR=/path/to/data python benchmarks/bench_simplify_quality.py [--percents 60 90]
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from simplification_eval import PERCENTS, phantom_cases, real_cases  # noqa: E402

from tumor3d.evaluation.simplification import (  # noqa: E402
    surface_distances,
    vertex_hausdorff,
    volume_change_percent,
)
from tumor3d.geometry.surface import is_watertight  # noqa: E402
from tumor3d.simplify import simplify_mesh  # noqa: E402

MODES = ("eager", "lazy")
KEYS = ("shd_vertex_mm", "hausdorff_mm", "mean_distance_mm", "volume_change_percent")


def measure(mesh, p: float, ring_update: str, n_samples: int) -> dict[str, float]:
    out = simplify_mesh(mesh, method="curvature", reduction_percent=p, ring_update=ring_update)
    row = {"faces_out": out.n_faces, "watertight": is_watertight(out)}
    row["volume_change_percent"] = volume_change_percent(mesh, out)
    row.update(vertex_hausdorff(mesh, out))
    row.update(surface_distances(mesh, out, n_samples=n_samples))
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--percents", type=float, nargs="+", default=list(PERCENTS))
    parser.add_argument("--n-samples", type=int, default=20000)
    args = parser.parse_args()
    data_dir = Path(os.environ.get("TUMOR3D_DATA_DIR", ROOT.parent / "shared" / "data"))
    cases = list(phantom_cases()) + list(real_cases(data_dir))
    print(
        "| case | P (%) | faces eager / lazy | Eq. 11 SHD (mm) | surface Hausdorff (mm) "
        "| mean distance (mm) | dV (%) | watertight |"
    )
    print("|---|---:|---:|---:|---:|---:|---:|:-:|")
    same = {m: {k: [] for k in KEYS} for m in MODES}
    for case, mesh in cases:
        for p in args.percents:
            r = {m: measure(mesh, p, m, args.n_samples) for m in MODES}
            e, lz = r["eager"], r["lazy"]
            print(
                f"| {case} | {p:.0f} | {e['faces_out']:,} / {lz['faces_out']:,} "
                f"| {e['shd_vertex_mm']:.2f} / {lz['shd_vertex_mm']:.2f} "
                f"| {e['hausdorff_mm']:.2f} / {lz['hausdorff_mm']:.2f} "
                f"| {e['mean_distance_mm']:.4f} / {lz['mean_distance_mm']:.4f} "
                f"| {e['volume_change_percent']:+.2f} / {lz['volume_change_percent']:+.2f} "
                f"| {e['watertight']} / {lz['watertight']} |",
                flush=True,
            )
            if e["faces_out"] == lz["faces_out"]:
                for m in MODES:
                    for k in KEYS:
                        same[m][k].append(r[m][k])
    n = len(same["lazy"][KEYS[0]])
    print(f"\nmeans over the {n} rows with equal face counts (eager -> lazy):")
    for k in KEYS:
        print(f"  {k}: {np.mean(same['eager'][k]):.4f} -> {np.mean(same['lazy'][k]):.4f}")


if __name__ == "__main__":
    main()
