"""Per-slice Dice by the size of the reference's cross-section, out of fold (issue 28).

A measurement, not a choice: on a saved ``learned_cv.py --cnn-folds ... --save-prob``
run, each FLAIR case's reference slices are binned by their tumour area as a share of
the case's largest cross-section, and each bin's mean per-slice Dice is given for the
shipped lesion (the forest + U-Net mean, cut as the run cut it), for the forest's and
the U-Net's maps alone (cut at 0.5, no other step), with the share of the bin's slices
the shipped lesion leaves empty and the share of the group's per-slice Dice loss
(``1 - Dice``, summed) the bin holds. The per-slice Dice of ``learned_cv.score`` is the
mean over the reference's tumour slices, each weighing the same, so a small
cross-section missed costs as much as a large one. (The ``all`` row pools the group's
slices; the reports' per-slice Dice is the mean of the cases' means.)

Usage::

    TUMOR3D_DATA_DIR=../shared/data python benchmarks/slice_size_survey.py \\
        --rows learned.json --prob prob --cache /tmp/cv-cache
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from learned_cv import add_recut_arguments, recut_rows  # noqa: E402

from tumor3d.config import parse_config  # noqa: E402
from tumor3d.evaluation.metrics import dice  # noqa: E402

#: Bins of a reference cross-section's area, as a share of the case's largest.
BINS = ((0.0, 0.1), (0.1, 0.25), (0.25, 0.5), (0.5, 1.0))
GROUPS = ("brats_flair", "lgg")


def slice_rows(rows: list[dict], args, cfg) -> list[dict]:
    """One row per reference tumour slice of each FLAIR case: its area share and the Dice
    of the shipped lesion, the forest's map and the U-Net's map on it."""
    flair = [r for r in rows if r["group"] in GROUPS]
    out = []
    for r, p, maps, mask in recut_rows(flair, args, cfg):
        areas = p.ref.sum(axis=(1, 2))
        for k in np.flatnonzero(areas):
            out.append(
                {
                    "case": r["case"],
                    "group": r["group"],
                    "share": float(areas[k] / areas.max()),
                    "shipped": dice(mask[k], p.ref[k]),
                    "forest": dice(maps["forest"][k] >= 0.5, p.ref[k]),
                    "cnn": dice(maps["cnn"][k] >= 0.5, p.ref[k]),
                    "empty": not mask[k].any(),
                }
            )
    return out


def table(srows: list[dict]) -> str:
    """The bins' figures per group (markdown)."""
    out = [
        "| group | area share of the largest slice | slices | shipped lesion | forest alone "
        "| U-Net alone | left empty | share of the group's Dice loss |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for g in GROUPS:
        rs = [s for s in srows if s["group"] == g]
        if not rs:
            continue
        loss = sum(1.0 - s["shipped"] for s in rs)
        for i, (lo, hi) in enumerate(BINS):
            last = i == len(BINS) - 1
            b = [s for s in rs if lo <= s["share"] < hi or (last and s["share"] == hi)]
            if not b:
                continue
            m = {k: float(np.mean([s[k] for s in b])) for k in ("shipped", "forest", "cnn")}
            out.append(
                f"| {g} | {lo:g}-{hi:g} | {len(b)} | {m['shipped']:.3f} | {m['forest']:.3f} "
                f"| {m['cnn']:.3f} | {np.mean([s['empty'] for s in b]):.2f} "
                f"| {sum(1.0 - s['shipped'] for s in b) / loss:.2f} |"
            )
        out.append(
            f"| {g} | all | {len(rs)} | {np.mean([s['shipped'] for s in rs]):.3f} "
            f"| {np.mean([s['forest'] for s in rs]):.3f} | {np.mean([s['cnn'] for s in rs]):.3f} "
            f"| {np.mean([s['empty'] for s in rs]):.2f} | 1.00 |"
        )
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", required=True, help="the run's learned_cv.py --json rows")
    add_recut_arguments(ap)
    args = ap.parse_args(argv)
    cfg = parse_config(Path(args.config).read_text(), source=args.config)
    srows = slice_rows(json.loads(Path(args.rows).read_text()), args, cfg)
    print(table(srows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
