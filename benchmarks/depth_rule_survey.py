"""Step 3b of the lesion model (``tumor3d.segmentation.lesion``): how deep do candidates reach?

Lists every candidate lesion of every case of ``benchmarks/real_segmentation.py``
*before* the depth rule (steps 2, 3, 3c and 6 of ``tumor3d/segmentation/lesion.py``: the
significant asymmetric seed components, all of them, not only the largest),
at 2 mm every 5 mm and at the native slices, with its depth percentiles
divided by the brain's median depth, and whether it lies in the reference
(at least half of its voxels). Then, per percentile, the smallest value of a
case's tumour (its largest candidate in the reference) and the largest value
of a false candidate that the rule rejects at the 75th percentile (the
superficial ones the rule exists for). ``reports/segmentation.md`` gives the
figures and the choice of ``tumor3d.segmentation.lesion.DEPTH_PERCENTILE``.

Usage::

    TUMOR3D_DATA_DIR=/work/shared/data python benchmarks/depth_rule_survey.py [--list]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

import real_segmentation as rs  # noqa: E402

from tumor3d.imaging.preprocess import preprocess_volume  # noqa: E402
from tumor3d.segmentation.lesion import (  # noqa: E402
    left_right_axis,
    normal_model,
    symmetry_plane,
)
from tumor3d.segmentation.lesion.candidates import _candidates, _depth_mm  # noqa: E402
from tumor3d.segmentation.lesion.normal import _smooth_in_brain  # noqa: E402
from tumor3d.segmentation.lesion.pixels import _pixel_lengths  # noqa: E402

PERCENTILES = (50, 75, 90, 95, 100)


def survey(data: Path, cfg, native: bool) -> list[dict]:
    rows = []
    lp = cfg.detect.lesion
    for case in rs._cases(data):
        if native and (case.native_only or case.label is None):
            continue  # the same as the thick run
        scan, ref = rs.read_case(case)
        if native or case.native_only or ref is None:
            img, step = scan.image, scan.slice_step_mm
        else:
            img = rs.emulate_thick(scan.image, 2)
            ref = rs.emulate_thick(ref.astype(np.float64), 2) >= 0.5
            step = rs.STEP * scan.slice_step_mm
        spacing = (step, *scan.pixel_spacing_mm)
        pre = preprocess_volume(img, **cfg.preprocess.model_dump(), spacing_mm=spacing)
        enhanced, brain = pre.enhanced, pre.brain_mask
        px = _pixel_lengths(spacing, lp.smoothing_mm, lp.min_region_mm2, lp.boundary_mm)
        sm = _smooth_in_brain(enhanced, brain, px.smoothing)
        model = normal_model(sm, enhanced, brain, lp.seed_sigmas, case.modality)
        axis = left_right_axis(scan.affine)
        plane = None if axis is None else symmetry_plane(sm, brain, model, axis, spacing)
        # every candidate before the decision rules: no depth (3b, spacing None) and no
        # contrast test (3e, the default contrast=False), so the survey sees them all
        _, labels, ids, _, _, _ = _candidates(
            model, sm, enhanced, brain, px.smoothing, px.min_region, lp.min_slices,
            False, None, plane, spacing,
        )  # fmt: skip
        depth = _depth_mm(brain, spacing)
        brain_median = float(np.median(depth[brain]))
        for k, i in enumerate(ids):
            comp = labels == i
            inside = float((comp & ref).sum() / comp.sum()) if ref is not None else 0.0
            rows.append({
                "case": case.name + (" (1 mm)" if native else ""),
                "rank": k,
                "ml": float(comp.sum()) * float(np.prod(spacing)) / 1000.0,
                "ratio": np.percentile(depth[comp], PERCENTILES) / brain_median,
                "tumour": inside >= 0.5,
            })  # fmt: skip
    return rows


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--list", action="store_true", help="print every candidate")
    args = ap.parse_args(argv)
    data = rs.real_data_or_skip()
    if data is None:
        return 0
    cfg = rs.default_config()
    rows = survey(data, cfg, native=False) + survey(data, cfg, native=True)
    if args.list:
        for r in rows:
            kind = "tumour" if r["tumour"] else "false"
            ratios = " ".join(f"{v:4.2f}" for v in r["ratio"])
            print(f"{r['case']:<36} #{r['rank']} {r['ml']:6.2f} mL {kind:<6} {ratios}")
    j75 = PERCENTILES.index(75)
    largest = [r for r in rows if r["tumour"] and r["rank"] == min(
        q["rank"] for q in rows if q["case"] == r["case"] and q["tumour"])]  # fmt: skip
    superficial = [r for r in rows if not r["tumour"] and r["ratio"][j75] < 1.0]
    print(f"{len([r for r in rows if r['tumour']])} tumour candidates, "
          f"{len([r for r in rows if not r['tumour']])} false ones "
          f"({len(superficial)} rejected by the 75th percentile)")  # fmt: skip
    if not largest or not superficial:
        print("no tumour candidate or no superficial false one: nothing to compare")
        return 0
    print("| percentile | smallest ratio of a case's tumour | largest ratio of those false ones |")
    print("|---|---|---|")
    for j, p in enumerate(PERCENTILES):
        t = min(largest, key=lambda r: r["ratio"][j])
        f = max(superficial, key=lambda r: r["ratio"][j])
        print(f"| {p} | {t['ratio'][j]:.2f} ({t['case']}) | {f['ratio'][j]:.2f} ({f['case']}) |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
