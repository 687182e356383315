"""Nested choice: the lesion closed slice by slice before it is measured (issue 28).

On BraTS FLAIR the shipped method's volumes are short (median -11 %, 7 of 11
below the reference): the whole-tumour label holds the tumour's core, which
FLAIR can show darker than the oedema around it, and the cut follows the bright
part. A hole enclosed in a slice is already filled (``keep_main_lesion``); a
dark part that opens onto the lesion's edge is not. A morphological closing in
each slice fills such bays up to its radius. A grid fixed before any fold was
scored, on the saved out-of-fold maps of a ``learned_cv.py --save-prob`` run
(and the robust method's masks in the prepared-case cache, the default on T2):

* ``shipped``: the lesion as the pipeline makes it;
* ``close R``: that lesion closed in each slice by a disc of radius R mm
  (R in 2, 4, 6; the slice padded first, so nothing is lost at its edge), its
  holes filled again.

FLAIR: the forest + U-Net mean cut as shipped (``keep_main_lesion`` at 0.5, keep
fraction 1.0, the least region, ``segment.min_tumor_pixels``); T2: the robust
method's mask (the T2 default, ``segment.method: auto``). Scored by
:func:`learned_cv.score`. Nested by patient on the run's 5 folds as in
``prior_select.py``: FLAIR by ``cut_select``'s objective (0.5 BraTS FLAIR 3-D
Dice + 0.5 LGG per-slice Dice; tie: the lower mean absolute volume error), T2 by
the BraTS T2 cases' mean 3-D Dice (same tie).

The rule that would ship a setting, fixed before scoring
(``reports/learned_cv.md``, "The lesion closed slice by slice"): on FLAIR, held out
and paired, the BraTS FLAIR 3-D Dice or the LGG per-slice Dice gains at least 0.01
while neither loses more than 0.005, LGG slice recall and specificity stay at or
above 0.90 / 0.95, neither group's mean absolute volume error rises by more than 2
points and the FLAIR phantoms lose at most 0.01 of 3-D Dice; on T2, the nested
choice beats the robust mask by at least 0.01 of 3-D Dice with its mean absolute
volume error at most 2 points higher and the T2 phantoms losing at most 0.01.

Usage::

    TUMOR3D_DATA_DIR=../shared/data nice -n 10 python benchmarks/closing_select.py \\
        --rows-in learned.json --prob prob --cache /tmp/cv-cache --scored closing_rows.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from cut_select import add_scoring_arguments, scored_settings  # noqa: E402
from prior_select import report  # noqa: E402

SETTINGS = ("shipped", "close 2", "close 4", "close 6")


def close_slices(mask: np.ndarray, pixel_mm: tuple[float, float], radius_mm: float) -> np.ndarray:
    """``mask`` (z, y, x) closed in each slice by a disc of ``radius_mm``, holes filled.

    >>> m = np.zeros((1, 20, 20), bool); m[0, 5:15, 5:15] = True; m[0, 8:12, 5:10] = False
    >>> int(m.sum()), int(close_slices(m, (1.0, 1.0), 3.0).sum())  # a bay 4 px wide, its mouth open
    (80, 96)
    >>> bool((close_slices(m, (1.0, 1.0), 1.5) == m).all())  # a disc narrower than the bay
    True
    """
    from scipy import ndimage as ndi

    from tumor3d.imaging.preprocess import fill_holes_per_slice

    if radius_mm <= 0:
        return mask
    ry, rx = radius_mm / pixel_mm[0], radius_mm / pixel_mm[1]
    hy, hx = int(np.floor(ry)), int(np.floor(rx))
    yy, xx = np.mgrid[-hy : hy + 1, -hx : hx + 1]
    disc = (yy / ry) ** 2 + (xx / rx) ** 2 <= 1.0
    pad = max(hy, hx) + 1
    out = mask.copy()
    for k in np.flatnonzero(mask.any(axis=(1, 2))):
        closed = ndi.binary_closing(np.pad(mask[k], pad), structure=disc)
        out[k] |= closed[pad:-pad, pad:-pad]
    return fill_holes_per_slice(out)


def score_settings(rows_in: list[dict], prob_dir: Path, cache: str, cfg) -> dict[str, list[dict]]:
    """Every setting's scored rows: FLAIR (the forest + U-Net maps) and T2 (the robust masks)."""
    from types import SimpleNamespace

    import learned_cv as L

    from tumor3d.storage.manifest import data_dir

    shipped = SimpleNamespace(threshold=0.5, t1c_threshold=None, keep_fraction=1.0)

    n_ph = sum(r["case"].startswith("phantom/") for r in rows_in) // 2
    specs = {s.name: s for s in L.case_specs(data_dir()) + L.phantom_specs(n_ph)}
    out: dict[str, list[dict]] = {}
    for r in rows_in:
        if r["group"] not in ("brats_flair", "lgg", "phantom", "brats_t2"):
            continue
        with np.load(L.case_file(prob_dir, r["case"])) as z:
            flair = "cnn" in z.files
            if flair:
                m = 0.5 * z["forest"].astype(np.float32) + 0.5 * z["cnn"].astype(np.float32)
        p = L.cached_prepare(specs[r["case"]], cfg, True, cache)
        if flair:
            family, group = "flair", r["group"]
            lesion = L._final_mask(p, m, shipped, cfg)  # the run's own cut of its map
        else:
            family = "t2"
            group = "phantom_t2" if r["group"] == "phantom" else r["group"]
            if p.prior is None:
                raise SystemExit(f"{r['case']}: the cache holds no robust mask (the prior)")
            lesion = p.prior.astype(bool)
        for s in SETTINGS:
            radius = 0.0 if s == "shipped" else float(s.split()[1])
            row = L.score(p, close_slices(lesion, p.pixel_mm, radius), cfg)
            row.update(fold=r["fold"], group=group)
            out.setdefault(f"{family}: {s}", []).append(row)
        print(f"  {r['case']}: {len(SETTINGS)} settings", flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_scoring_arguments(ap)
    args = ap.parse_args(argv)
    by_set = scored_settings(args, score_settings)
    print(report(by_set, list(range(args.folds))))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
