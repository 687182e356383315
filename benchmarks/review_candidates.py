"""Candidate review figures of the image and of the lesion's size, against the review's own.

Issue 28 item 5: the review flags 70 % of the cases whose volume is off by more
than 25 %, short of 80 %; the cases it misses are confident over-segmentations
of clinical LGG heads (``reports/learned_cv.md``). This asks whether figures
that do not come from the models' probability would separate them: for each
out-of-fold row of ``benchmarks/learned_cv.py --json`` the lesion is cut again
from the run's saved probability (as ``benchmarks/review_figures.py`` does), and

- ``in_q10``, ``in_median``: the 10th percentile and median of the lesion's
  intensity, normalised as the forest's features are (median and robust SD of
  the tissue deeper than 20 mm, the lesion left out); an over-segmentation
  takes in normal tissue, so its dim tail should fall;
- ``ring_median``, ``contrast``: the same on an in-plane ring 2-6 mm outside
  the lesion, and the lesion's median minus it;
- ``dim_share``: the share of the lesion below 1.5 robust SD;
- ``max_area_mm2``, ``n_slices``: the lesion's largest slice area and its
  number of slices (small lesions have the larger relative volume errors).

Printed: per figure, the area under the ROC curve of telling the real cases
off by more than 25 % from those within 10 % (0.5: no better than chance;
below 0.5: the other way round), beside the review's own figures.

Usage::

    TUMOR3D_DATA_DIR=../shared/data python benchmarks/review_candidates.py learned.json \\
        --prob prob/ --cache /tmp/cv-cache
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from learned_cv import (  # noqa: E402
    add_saved_run_arguments,
    case_specs,
    phantom_specs,
    saved_lesion,
)

from tumor3d.config import parse_config  # noqa: E402
from tumor3d.learned.features import (  # noqa: E402
    REFERENCE_DEPTH_MM,
    _depth_mm,
    normalise_intensity,
    tissue_foreground,
)
from tumor3d.storage.manifest import data_dir  # noqa: E402

CANDIDATES = (
    "in_q10",
    "in_median",
    "ring_median",
    "contrast",
    "dim_share",
    "max_area_mm2",
    "n_slices",
)
REVIEW_FIGURES = ("mean_probability", "outside_ratio", "model_disagreement", "uncertain_ratio")


def candidate_figures(image: np.ndarray, lesion: np.ndarray, pixel_mm) -> dict[str, float]:
    """The candidates above for one case (``image``, ``lesion``: (z, y, x))."""
    tissue = tissue_foreground(image)
    depth = _depth_mm(tissue, pixel_mm)
    deep = depth >= REFERENCE_DEPTH_MM
    if deep.sum() < 100:
        deep = depth >= 0.5 * depth.max()
    norm = normalise_intensity(image, deep & ~lesion)
    area = lesion.sum(axis=(1, 2)) * float(np.prod(pixel_mm))
    out = {"max_area_mm2": float(area.max()), "n_slices": float(np.count_nonzero(area))}
    if not lesion.any():
        return {**out, **{k: float("nan") for k in CANDIDATES[:5]}}
    inside = norm[lesion]
    dist = np.full(lesion.shape, np.inf)
    for z in np.flatnonzero(area):
        dist[z] = ndi.distance_transform_edt(~lesion[z], sampling=pixel_mm)
    ring = (dist > 2.0) & (dist <= 6.0) & tissue
    ring_median = float(np.median(norm[ring])) if ring.any() else float("nan")
    in_median = float(np.median(inside))
    return {
        **out,
        "in_q10": float(np.percentile(inside, 10)),
        "in_median": in_median,
        "ring_median": ring_median,
        "contrast": in_median - ring_median,
        "dim_share": float(np.mean(inside < 1.5)),
    }


def auc(bad: np.ndarray, good: np.ndarray) -> float:
    """P(a bad case's figure > a good case's), ties counted half (finite values only)."""
    bad, good = bad[np.isfinite(bad)], good[np.isfinite(good)]
    if not len(bad) or not len(good):
        return float("nan")
    diff = bad[:, None] - good[None, :]
    return float(((diff > 0) + 0.5 * (diff == 0)).mean())


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("rows", help="learned_cv.py --json rows")
    add_saved_run_arguments(ap)
    args = ap.parse_args(argv)
    cfg = parse_config(Path(args.config).read_text(), source=args.config)
    rows = [r for r in json.loads(Path(args.rows).read_text()) if r["group"] != "phantom"]
    specs = {s.name: s for s in case_specs(data_dir()) + phantom_specs(0)}
    for r in rows:
        p, lesion = saved_lesion(specs[r["case"]], args, cfg)  # cut as the run cut it
        r.update(candidate_figures(p.image.astype(np.float32), lesion, p.pixel_mm))
    err = np.abs([r["vol_err"] for r in rows])
    bad, good = err > 25, err <= 10
    print(f"real cases: {bad.sum()} off by > 25 %, {good.sum()} within 10 %")
    print("| figure | AUC, > 25 % against within 10 % | median, > 25 % | median, within 10 % |")
    print("|---|---|---|---|")
    for name in CANDIDATES + REVIEW_FIGURES:
        v = np.array([np.nan if r.get(name) is None else float(r[name]) for r in rows])
        print(
            f"| {name} | {auc(v[bad], v[good]):.2f} | {np.nanmedian(v[bad]):.2f} "
            f"| {np.nanmedian(v[good]):.2f} |"
        )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
