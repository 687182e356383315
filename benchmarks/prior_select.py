"""Nested choice: the robust method's mask as a second say in the learned method's cut (issue 28).

The learned method already computes the robust lesion model's mask of every
patient (the forest's "prior" feature). Out of fold the two fail on different
BraTS cases (``reports/learned_cv.md``: pat0005's FLAIR 0.58 learned, 0.85
robust; Brats18_2013_3_1's 0.78 learned, 0.52 robust), so this asks whether
letting that mask move the final cut helps. A grid fixed before any fold was
scored, on the saved out-of-fold maps of a ``learned_cv.py --save-prob`` run:

* ``shipped``: the map cut at 0.5, as the pipeline does;
* ``or T``: the map above 0.5, or inside the robust mask and above ``T``
  (T in 0.3, 0.4: the map ``m + (0.5 - T) * prior``, clipped to 1, cut at 0.5);
* ``blend V``: ``(1 - V) * m + V * prior`` cut at 0.5 (V in 0.15, 0.3; on T2 also
  0.5, which keeps the robust mask where the forest scores at all).

``m`` is the shipped map: the forest + U-Net mean on FLAIR (keys ``forest`` and
``cnn``), the forest alone on T2 (key ``prob``). Each lesion is made and scored
as in ``cut_select.py`` (:func:`keep_main_lesion` with keep fraction 1.0, the
least region, ``segment.min_tumor_pixels``, :func:`learned_cv.score`).

Two nested choices on the run's 5 folds (chosen on four, scored on the fifth):
FLAIR by ``cut_select``'s objective (0.5 BraTS FLAIR 3-D Dice + 0.5 LGG
per-slice Dice; tie: the lower mean absolute volume error), T2 by the BraTS T2
cases' mean 3-D Dice (same tie). The other folds' maps come from models that saw
fold k's patients, as in ``cut_select.py``. The rule that would ship a setting
was fixed before scoring: ``reports/learned_cv.md``, "The robust mask as a
second say in the cut".

Usage::

    TUMOR3D_DATA_DIR=../shared/data nice -n 10 python benchmarks/prior_select.py \\
        --rows-in learned.json --prob prob --cache /tmp/cv-cache --scored prior_rows.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from cnn_select import group_line  # noqa: E402
from cut_select import add_scoring_arguments, nested_choice, paired, scored_settings  # noqa: E402

FLAIR_SETTINGS = ("shipped", "or 0.3", "or 0.4", "blend 0.15", "blend 0.3")
T2_SETTINGS = FLAIR_SETTINGS + ("blend 0.5",)
FLAIR_GROUPS = ("brats_flair", "lgg", "phantom")  # the phantoms reported, not chosen on
T2_GROUPS = ("brats_t2", "phantom_t2")


def second_say(m: np.ndarray, prior: np.ndarray, setting: str) -> np.ndarray:
    """The map to cut at 0.5 for ``setting`` (module docstring).

    >>> m = np.array([0.2, 0.35, 0.45, 0.6, 0.9], np.float32)
    >>> prior = np.array([1, 1, 1, 0, 0], bool)
    >>> for s in ("shipped", "or 0.3", "or 0.4"):
    ...     print((second_say(m, prior, s) > 0.5).astype(int))
    [0 0 0 1 1]
    [0 1 1 1 1]
    [0 0 1 1 1]
    >>> (second_say(m, prior, "blend 0.3") > 0.5).tolist()  # 0.7 m + 0.3 prior
    [False, True, True, False, True]
    """
    pr = prior.astype(np.float32)
    if setting == "shipped":
        return m
    kind, value = setting.split()
    v = float(value)
    if kind == "or":
        return np.minimum(m + (0.5 - v) * pr, 1.0).astype(np.float32)
    return ((1.0 - v) * m + v * pr).astype(np.float32)


def t2_objective(rows: list[dict], kind: str) -> tuple[float, float]:
    """(mean 3-D Dice, mean abs volume error) of the BraTS T2 rows.

    >>> t2_objective([{"group": "brats_t2", "dice3d": 0.7, "vol_err": -20},
    ...               {"group": "lgg", "dice3d": 0.1, "vol_err": 90}], "t2")
    (0.7, 20.0)
    """
    t2 = [r for r in rows if r["group"] == "brats_t2"]
    return (
        round(float(np.nanmean([r["dice3d"] for r in t2])), 12),
        float(np.nanmean([abs(r["vol_err"]) for r in t2])),
    )


def score_settings(rows_in: list[dict], prob_dir: Path, cache: str, cfg) -> dict[str, list[dict]]:
    """Every setting's scored rows (FLAIR settings on the FLAIR cases, T2 ones on T2)."""
    import learned_cv as L

    from tumor3d.learned.segment import keep_main_lesion
    from tumor3d.storage.manifest import data_dir

    n_ph = sum(r["case"].startswith("phantom/") for r in rows_in) // 2
    specs = {s.name: s for s in L.case_specs(data_dir()) + L.phantom_specs(n_ph)}
    out: dict[str, list[dict]] = {}
    worst = 0.0
    for r in rows_in:
        if r["group"] not in ("brats_flair", "lgg", "phantom", "brats_t2"):
            continue
        with np.load(L.case_file(prob_dir, r["case"])) as z:
            if "cnn" in z.files:
                m = 0.5 * z["forest"].astype(np.float32) + 0.5 * z["cnn"].astype(np.float32)
                family, settings = "flair", FLAIR_SETTINGS
            else:
                m = z["prob"].astype(np.float32)
                family, settings = "t2", T2_SETTINGS
        group = "phantom_t2" if (r["group"] == "phantom" and family == "t2") else r["group"]
        if family == "t2" and group not in T2_GROUPS:
            continue  # a FLAIR case scored by the forest alone: not in this run's shape
        p = L.cached_prepare(specs[r["case"]], cfg, True, cache)
        if p.prior is None:
            raise SystemExit(f"{r['case']}: the cache holds no robust mask (the prior)")
        for s in settings:
            prob = second_say(m, p.prior, s)
            mask = keep_main_lesion(prob, 0.5, keep_fraction=1.0, min_voxels=L._min_voxels(p))
            mask[mask.sum(axis=(1, 2)) < cfg.segment.min_tumor_pixels] = False
            row = L.score(p, mask, cfg)
            row.update(fold=r["fold"], group=group)
            out.setdefault(f"{family}: {s}", []).append(row)
            if s == "shipped":  # the run's own cut: its lesion must come back (float16 maps)
                d = abs(row["est_ml"] - r["est_ml"]) / max(r["est_ml"], 1e-9)
                worst = max(worst, d)
        print(f"  {r['case']}: {len(settings)} settings", flush=True)
    print(f"the shipped setting's lesions within {worst:.2%} of the run's volumes", flush=True)
    return out


def report(by_set: dict[str, list[dict]], folds: list[int]) -> str:
    out = []
    for family, groups, score in (
        ("flair", FLAIR_GROUPS, None),
        ("t2", T2_GROUPS, t2_objective),
    ):
        sets = {n: rs for n, rs in by_set.items() if n.startswith(family + ":")}
        if not sets:
            continue
        choice, inner = nested_choice(sets, folds, "targets", score)
        nested = [r for k in folds for r in sets[choice[k]] if r["fold"] == k]
        ship = sets[f"{family}: shipped"]
        out += [f"## {family}", "", "| outer fold | chosen | objective on the other folds "
                "(chosen / shipped) |", "|---|---|---|"]  # fmt: skip
        for k in folds:
            c, s = inner[k][choice[k]], inner[k][f"{family}: shipped"]
            out.append(f"| {k} | {choice[k]} | {c[0]:.4f} / {s[0]:.4f} |")
        out += ["", "| group | setting | n | 3-D Dice mean ± sd (median) | per-slice Dice | "
                "slice recall / spec. | volume error mean abs (median) | within 10 % / "
                "beyond 25 % |", "|---|---|---|---|---|---|---|---|"]  # fmt: skip
        for g in groups:
            for label, rs in [("nested choice", nested)] + list(sets.items()):
                rg = [r for r in rs if r["group"] == g]
                if rg:
                    out.append(group_line(g, label, rg))
        out += ["", "nested choice against the shipped cut, paired:", ""]
        out += paired(nested, ship, groups, wilcoxon_p=True)
        out.append("")
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_scoring_arguments(ap)
    args = ap.parse_args(argv)
    by_set = scored_settings(args, score_settings)
    print(report(by_set, list(range(args.folds))))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
