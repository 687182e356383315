"""A candidate doubt for the rule-based methods: a mask in both hemispheres.

A user audit (issue 28) ran the default on the BraTS T2 of Brats18_TCIA01_378_1 (the
robust method): Eq. 7 within 20 % of the reference, status ``ok``, 3-D Dice 0.34. Most
of the mask was the bright sulcal CSF of the *healthy* hemisphere, which the tumour's
mass effect had made look asymmetric. The candidate: the share of the mask on the
minority side of the brain's midline (per slice, the brain mask's centroid along the
left-right axis), ``minority``; a mask with a comparable part on each side of a head
is more often a bright bilateral structure (CSF, scalp) than a tumour.

For every labelled FLAIR and T2 case of ``../shared/data`` (and 10 + 10 phantoms), the
robust method's mask (as ``benchmarks/learned_cv.py --method robust`` makes it), its
3-D Dice and Eq. 7 error, and ``minority``. A case is *bad* when off by more than 25 %
or of 3-D Dice under 0.5, *good* when within 10 % and of Dice 0.5 or more. The limit
is chosen by nested cross-validation by patient (``learned_cv.assign_folds``): on four
folds, the candidate limit with the largest share of bad cases flagged less the share
of good cases flagged (ties: the higher limit); scored on the fifth.

Usage::

    TUMOR3D_DATA_DIR=../shared/data python benchmarks/bilateral_doubt.py \\
        --cache /tmp/cv-cache --json bilateral.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import learned_cv as cv  # noqa: E402

from tumor3d.config import parse_config  # noqa: E402
from tumor3d.imaging.preprocess import preprocess_volume  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
LIMITS = (0.2, 0.25, 0.3, 0.35, 0.4, 0.45)


def minority_share(mask: np.ndarray, brain: np.ndarray, lr_axis: int | None) -> float:
    """The share of ``mask`` (z, y, x) on the side of each slice's brain midline that
    holds less of it; NaN without a left-right axis or a mask."""
    if lr_axis is None or not mask.any():
        return float("nan")
    sides = np.zeros(2, dtype=np.int64)
    for z in range(mask.shape[0]):
        if not mask[z].any() or not brain[z].any():
            continue
        mid = np.nonzero(brain[z])[lr_axis - 1].mean()
        cols = np.nonzero(mask[z])[lr_axis - 1]
        sides += [int((cols < mid).sum()), int((cols >= mid).sum())]
    return float(sides.min() / max(1, sides.sum()))


def nested_choice(rows: list[dict], folds: int) -> tuple[list[dict], int, int, int, int]:
    """Per held-out fold, the limit chosen on the others and the cases it flags."""

    def gain(rs: list[dict], t: float) -> float:
        bad = [r for r in rs if r["bad"]]
        good = [r for r in rs if r["good"]]
        return sum(r["minority"] > t for r in bad) / max(1, len(bad)) - sum(
            r["minority"] > t for r in good
        ) / max(1, len(good))

    per_fold, fb, nb, fg, ng = [], 0, 0, 0, 0
    for k in range(folds):
        train = [r for r in rows if r["fold"] != k]
        test = [r for r in rows if r["fold"] == k]
        t = max(LIMITS, key=lambda t: (round(gain(train, t), 9), t))
        flagged = [r["case"] for r in test if r["minority"] > t]
        per_fold.append({"fold": k, "limit": t, "flagged": flagged})
        fb += sum(r["minority"] > t for r in test if r["bad"])
        nb += sum(r["bad"] for r in test)
        fg += sum(r["minority"] > t for r in test if r["good"])
        ng += sum(r["good"] for r in test)
    return per_fold, fb, nb, fg, ng


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cache", default=None, help="learned_cv.py's preparation cache")
    ap.add_argument("--config", default=str(ROOT / "configs" / "default.yaml"))
    ap.add_argument("--phantoms", type=int, default=10)
    ap.add_argument("--json", default=None, help="write the per-case rows here")
    args = ap.parse_args(argv)
    data = cv.data_dir()
    if not data.is_dir():
        print(f"skipped: no real data at {data} (set TUMOR3D_DATA_DIR)")
        return 0
    cfg = parse_config(Path(args.config).read_text(), source=args.config)
    specs = cv.case_specs(data) + cv.phantom_specs(args.phantoms)
    folds = cv.assign_folds(specs, 5)
    rows = []
    for s in specs:
        if s.modality not in ("flair", "t2"):
            continue
        p = cv.cached_prepare(s, cfg, False, args.cache)
        pre = preprocess_volume(p.image, **cfg.preprocess.model_dump(), spacing_mm=p.spacing_mm)
        mask = cv.robust_mask(pre, s.modality, p.spacing_mm, p.lr_axis, cfg)
        r = cv.score(p, mask, cfg)
        r["minority"] = minority_share(mask, np.asarray(pre.brain_mask, bool), p.lr_axis)
        r["fold"] = folds[s.patient]
        r["bad"] = bool(abs(r["vol_err"]) > 25 or r["dice3d"] < 0.5)
        r["good"] = bool(abs(r["vol_err"]) <= 10 and r["dice3d"] >= 0.5)
        rows.append(r)
        print(
            f"  {r['case']}: 3d {r['dice3d']:.3f} vol {r['vol_err']:+.1f}% "
            f"minority {r['minority']:.3f}",
            flush=True,
        )
    real = [r for r in rows if r["group"] != "phantom" and not math.isnan(r["minority"])]
    phantoms = [r["minority"] for r in rows if r["group"] == "phantom"]
    print(f"phantoms: largest minority share {np.nanmax(phantoms):.3f}")
    for t in LIMITS:
        fb = sum(r["minority"] > t for r in real if r["bad"])
        fg = sum(r["minority"] > t for r in real if r["good"])
        nb, ng = sum(r["bad"] for r in real), sum(r["good"] for r in real)
        print(f"limit {t:.2f} (all rows, not a held-out figure): bad {fb}/{nb}, good {fg}/{ng}")
    per_fold, fb, nb, fg, ng = nested_choice(real, 5)
    for f in per_fold:
        print(
            f"fold {f['fold']}: limit {f['limit']:.2f} chosen on the others; flags {f['flagged']}"
        )
    print(f"held out: bad flagged {fb}/{nb}, good flagged {fg}/{ng}")
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
