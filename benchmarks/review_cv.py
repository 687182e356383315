"""Choose the learned method's review limits by cross-validation by patient.

Reads the per-case rows of ``benchmarks/learned_cv.py --json`` (out-of-fold:
every case was segmented by a model that never saw its patient) and, fold by
fold, chooses the limits of :data:`tumor3d.learned.review.REVIEW_LIMITS` on
the other folds' cases, then judges them on the held-out fold:

- a case whose volume is off by more than 25 % should be flagged (target:
  >= 80 % of them),
- a case within 10 % should not (target: <= 25 % flagged).

The choice maximises the share of > 25 % cases flagged among the limits
that flag at most 25 % of the within-10 % cases of the choosing folds
(ties: fewer flags). The final limits are chosen the same way on every case.

Usage::

    python benchmarks/review_cv.py /tmp/cv/learned.json
"""

from __future__ import annotations

import itertools
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tumor3d.learned.review import review_segmentation  # noqa: E402

GRID = {
    "uncertain_ratio": (0.4, 0.5, 0.6, 0.7, 0.8, 1.0, 1.2, 1.5, 2.0, 3.0),
    "mean_probability": (0.5, 0.6, 0.7, 0.75, 0.8, 0.85),
    "outside_ratio": (0.1, 0.2, 0.3, 0.5, 0.75, 1.0, 2.0),
    "prior_agreement": (0.0, 0.3, 0.5, 0.6, 0.7, 0.8),
}
MAX_GOOD_FLAGGED = 0.25


def flags(rows: list[dict], limits: dict) -> np.ndarray:
    out = []
    for r in rows:
        fig = {
            k: (float("inf") if r[k] is None else float(r[k]))
            for k in ("uncertain_ratio", "outside_ratio")
        }
        mp = r["mean_probability"]
        fig["mean_probability"] = float("nan") if mp is None else float(mp)
        fig["volume_ml"] = 0.0
        fig["prior_agreement"] = float(r.get("prior_agreement", 1.0))
        out.append(review_segmentation(fig, limits).needs_review)
    return np.array(out, bool)


def rates(rows: list[dict], f: np.ndarray) -> tuple[float, float, int, int]:
    err = np.abs(np.array([r["vol_err"] for r in rows], float))
    bad, good = err > 25, err <= 10
    return (
        float(f[bad].mean()) if bad.any() else float("nan"),
        float(f[good].mean()) if good.any() else float("nan"),
        int(bad.sum()),
        int(good.sum()),
    )


def choose(rows: list[dict]) -> dict:
    best, best_key = None, None
    for values in itertools.product(*GRID.values()):
        lim = dict(zip(GRID, values, strict=True))
        f = flags(rows, lim)
        caught, false, _, _ = rates(rows, f)
        if not false <= MAX_GOOD_FLAGGED:
            continue
        key = (caught, -f.mean())
        if best_key is None or key > best_key:
            best, best_key = lim, key
    return best or {
        "uncertain_ratio": 3.0,
        "mean_probability": 0.5,
        "outside_ratio": 2.0,
        "prior_agreement": 0.0,
    }


def cross_validate(rows: list[dict]) -> dict:
    """Limits chosen fold by fold on the other folds, judged on the held-out fold.

    Returns ``lines`` (the printed report), ``all`` and ``real`` (every case;
    the cases but the phantoms): ``(share of the > 25 % cases flagged, share of
    the within-10 % cases flagged, number of each)``, ``fold_limits`` and
    ``final`` (the limits chosen on every case).
    """
    rows = [r for r in rows if np.isfinite(r["vol_err"])]
    folds = sorted({r["fold"] for r in rows})
    held_flags = np.zeros(len(rows), bool)
    lines, fold_limits = [], {}
    for k in folds:
        train = [r for r in rows if r["fold"] != k]
        lim = fold_limits[k] = choose(train)
        idx = [i for i, r in enumerate(rows) if r["fold"] == k]
        held_flags[idx] = flags([rows[i] for i in idx], lim)
        lines.append(f"fold {k}: limits {lim}")
    caught, false, n_bad, n_good = every = rates(rows, held_flags)
    lines.append(
        f"\ncross-validated: {caught:.0%} of {n_bad} cases off by > 25 % flagged; "
        f"{false:.0%} of {n_good} within 10 % flagged"
    )
    for g in sorted({r["group"] for r in rows}):
        sel = [i for i, r in enumerate(rows) if r["group"] == g]
        c, fl, nb, ng = rates([rows[i] for i in sel], held_flags[sel])
        lines.append(f"  {g}: {c:.0%} of {nb} > 25 % flagged, {fl:.0%} of {ng} within 10 % flagged")
    real = [i for i, r in enumerate(rows) if r["group"] != "phantom"]
    real_rates = caught, false, n_bad, n_good = rates([rows[i] for i in real], held_flags[real])
    if len(real) < len(rows):
        lines.append(
            f"  real cases only: {caught:.0%} of {n_bad} > 25 % flagged, {false:.0%} of "
            f"{n_good} within 10 % flagged"
        )
    final = choose(rows)
    lines.append(f"\nfinal limits (every case): {final}")
    return {
        "lines": lines,
        "all": every,
        "real": real_rates,
        "fold_limits": fold_limits,
        "final": final,
    }


def main(argv=None) -> int:
    args = sys.argv[1:] if argv is None else argv
    out = cross_validate(json.loads(Path(args[0]).read_text()))
    print("\n".join(out["lines"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
