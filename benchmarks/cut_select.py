"""Nested choice of the forest + U-Net mean's cut, weight and keep fraction (issue 28).

The shipped FLAIR method averages the forest's and the U-Net's probabilities and
cuts the mean at the forest's own threshold and keep fraction, which nested
cross-validation chose for the forest alone (``reports/learned_cv.md``). The
mean is smoother, so its best cut may differ. This scores a small grid, fixed
before any fold was scored, on the saved out-of-fold maps of the shipped run
(``learned_cv.py --cnn-folds ... --save-prob``: keys ``forest`` and ``cnn``):

* threshold t in {0.4, 0.45, 0.5, 0.55};
* the net's weight w in {0.5, 0.65}: ``prob = (1 - w) * forest + w * cnn``;
* keep fraction in {1.0 (the shipped model's), 0.3 (keep_main_lesion's default)}.

Each case's lesion is made as the pipeline makes it
(:func:`tumor3d.learned.segment.keep_main_lesion` with the case's least region,
then ``segment.min_tumor_pixels``) and scored by :func:`learned_cv.score`
(per-slice Dice, slice recall / specificity, 3-D Dice of the interpolated stack
for BraTS, voxel Dice for the native LGG heads, Eq. 7 volume error).

The choice is nested by patient on the run's 5 folds: for outer fold k the
setting with the highest objective over the OTHER folds' cases is chosen and
fold k is scored with it. The objective (fixed before scoring) is the targets'
own figures of the two FLAIR groups, each group weighing the same:
``0.5 * mean 3-D Dice (brats_flair) + 0.5 * mean per-slice Dice (lgg)``; ties:
the lower mean absolute volume error of the two groups, then the grid order
(the shipped setting first). ``--objective pooled3d`` is ``cnn_select.py``'s
(mean 3-D Dice over the pooled cases), a sensitivity check. As in
``cnn_select.py`` the other folds' maps come from models that saw fold k's
patients in training (a fully nested choice would retrain every inner model).

Usage (``reports/learned_cv.md``, "The mean's cut, nested")::

    TUMOR3D_DATA_DIR=../shared/data nice -n 10 python benchmarks/cut_select.py \\
        --rows-in learned.json --prob prob --cache /tmp/cv-cache --scored cut_rows.json

``--scored`` keeps every setting's rows: a second run with the same file only selects.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from cnn_select import group_line  # noqa: E402  (the same table row)

THRESHOLDS = (0.5, 0.4, 0.45, 0.55)  # the shipped value first (the last tie-break)
NET_WEIGHTS = (0.5, 0.65)
KEEP_FRACTIONS = (1.0, 0.3)
SETTINGS = tuple(itertools.product(THRESHOLDS, NET_WEIGHTS, KEEP_FRACTIONS))
SHIPPED = (0.5, 0.5, 1.0)
GROUPS = ("brats_flair", "lgg")  # the FLAIR groups of the objective
REPORTED = ("brats_flair", "lgg", "phantom")  # FLAIR phantoms too (not in the objective)


def key(s) -> str:
    return f"t={s[0]:g} w={s[1]:g} kf={s[2]:g}"


def objective(rows: list[dict], kind: str) -> tuple[float, float]:
    """(objective, mean abs volume error over the FLAIR groups) of ``rows``.

    >>> r = [{"group": "brats_flair", "dice3d": 0.8, "slice_dice": 0.1, "vol_err": 10},
    ...      {"group": "lgg", "dice3d": 0.2, "slice_dice": 0.6, "vol_err": -30}]
    >>> objective(r, "targets")
    (0.7, 20.0)
    >>> objective(r, "pooled3d")
    (0.5, 20.0)
    """
    fl = [r for r in rows if r["group"] in GROUPS]
    err = float(np.nanmean([abs(r["vol_err"]) for r in fl]))
    if kind == "pooled3d":
        return round(float(np.nanmean([r["dice3d"] for r in fl])), 12), err
    b = np.nanmean([r["dice3d"] for r in fl if r["group"] == "brats_flair"])
    s = np.nanmean([r["slice_dice"] for r in fl if r["group"] == "lgg"])
    return round(float(0.5 * b + 0.5 * s), 12), err


def nested_choice(by_set: dict[str, list[dict]], folds: list[int], kind: str, score=None):
    """Per outer fold: the setting (a key of ``by_set``) chosen on the other folds' rows
    (by ``score(rows, kind)``: :func:`objective` unless given).

    >>> r = lambda f, g, d: {"fold": f, "group": g, "dice3d": d, "slice_dice": d, "vol_err": 0}
    >>> by = {"a": [r(0, "lgg", 0.9), r(1, "lgg", 0.1)], "b": [r(0, "lgg", 0.2), r(1, "lgg", 0.8)]}
    >>> nested_choice(by, [0, 1], "pooled3d")[0]
    {0: 'b', 1: 'a'}
    """
    score = objective if score is None else score
    names = list(by_set)
    choice, inner = {}, {}
    for k in folds:
        inner[k] = {n: score([r for r in by_set[n] if r["fold"] != k], kind) for n in names}
        choice[k] = min(names, key=lambda n: (-inner[k][n][0], inner[k][n][1], names.index(n)))  # noqa: B023
    return choice, inner


def score_settings(rows_in: list[dict], prob_dir: Path, cache: str, cfg) -> dict[str, list[dict]]:
    """Every setting's scored rows of the FLAIR cases that have the two maps."""
    import learned_cv as L

    from tumor3d.learned.segment import keep_main_lesion
    from tumor3d.storage.manifest import data_dir

    n_ph = sum(r["case"].startswith("phantom/") for r in rows_in) // 2
    specs = {s.name: s for s in L.case_specs(data_dir()) + L.phantom_specs(n_ph)}
    out: dict[str, list[dict]] = {key(s): [] for s in SETTINGS}
    worst = 0.0
    for r in rows_in:
        if r["group"] not in REPORTED:
            continue
        path = L.case_file(prob_dir, r["case"])
        with np.load(path) as z:
            if "cnn" not in z.files:
                continue  # the forest alone (T2 phantoms)
            forest, cnn = z["forest"].astype(np.float32), z["cnn"].astype(np.float32)
        p = L.cached_prepare(specs[r["case"]], cfg, True, cache)
        for s in SETTINGS:
            t, w, kf = s
            prob = ((1.0 - w) * forest + w * cnn).astype(np.float32)
            mask = keep_main_lesion(prob, t, keep_fraction=kf, min_voxels=L._min_voxels(p))
            mask[mask.sum(axis=(1, 2)) < cfg.segment.min_tumor_pixels] = False
            row = L.score(p, mask, cfg)
            row["fold"] = r["fold"]
            out[key(s)].append(row)
            if s == SHIPPED:  # the run's own cut: the row must come back (float16 maps)
                d = abs(row["est_ml"] - r["est_ml"]) / max(r["est_ml"], 1e-9)
                worst = max(worst, d)
        print(f"  {r['case']}: {len(SETTINGS)} settings", flush=True)
    print(f"shipped setting's lesions within {worst:.2%} of the run's volumes", flush=True)
    return out


def paired(
    after: list[dict], before: list[dict], groups=REPORTED, *, wilcoxon_p: bool = False
) -> list[str]:
    """Per group: paired change of the target figures, nested choice against the shipped cut
    (``wilcoxon_p``: each Dice change with its Wilcoxon signed-rank p)."""
    from scipy.stats import wilcoxon

    def pv(d: np.ndarray) -> str:
        d = d[np.abs(d) > 1e-12]
        if not wilcoxon_p:
            return ""
        return f" ({float(wilcoxon(d).pvalue):.2g})" if d.size >= 2 else " (nan)"

    b = {r["case"]: r for r in before}
    p_head = " (p)" if wilcoxon_p else ""
    out = [
        f"| group | n | 3-D Dice change mean ± sd{p_head} | better / worse by > 0.01 | per-slice "
        f"Dice change mean ± sd{p_head} | slice recall change | slice spec. change | abs. volume "
        "error change |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for g in groups:
        pr = [(r, b[r["case"]]) for r in after if r["group"] == g]
        if not pr:
            continue
        d3 = np.array([x["dice3d"] - y["dice3d"] for x, y in pr])
        ds = np.array([x["slice_dice"] - y["slice_dice"] for x, y in pr])
        rc = np.nanmean([x["recall"] - y["recall"] for x, y in pr])
        sp = np.nanmean([x["spec"] - y["spec"] for x, y in pr])
        ve = np.nanmean([abs(x["vol_err"]) - abs(y["vol_err"]) for x, y in pr])
        out.append(
            f"| {g} | {len(pr)} | {np.nanmean(d3):+.3f} ± {np.nanstd(d3):.3f}{pv(d3)} | "
            f"{int(np.sum(d3 > 0.01))} / {int(np.sum(d3 < -0.01))} | "
            f"{np.nanmean(ds):+.3f} ± {np.nanstd(ds):.3f}{pv(ds)} | {rc:+.3f} | {sp:+.3f} | "
            f"{ve:+.1f} pt |"
        )
    return out


def report(by_set: dict[str, list[dict]], folds: list[int], kind: str) -> str:
    choice, inner = nested_choice(by_set, folds, kind)
    nested = [r for k in folds for r in by_set[choice[k]] if r["fold"] == k]
    counts = {n: sum(c == n for c in choice.values()) for n in by_set}
    obj = (
        "0.5 BraTS FLAIR 3-D Dice + 0.5 LGG per-slice Dice"
        if kind == "targets"
        else ("pooled 3-D Dice of the FLAIR cases (cnn_select.py's)")
    )
    out = [f"objective: {obj}", "", "| outer fold | chosen | objective on the other folds "
           "(chosen / shipped) |", "|---|---|---|"]  # fmt: skip
    for k in folds:
        c, s = inner[k][choice[k]], inner[k][key(SHIPPED)]
        out.append(f"| {k} | {choice[k]} | {c[0]:.4f} / {s[0]:.4f} |")
    out += [
        "",
        "chosen: " + ", ".join(f"{n} in {c} of {len(folds)}" for n, c in counts.items() if c),
    ]
    out += [
        "",
        "| group | cut | n | 3-D Dice mean ± sd (median) | per-slice Dice | slice recall / "
        "spec. | volume error mean abs (median) | within 10 % / beyond 25 % |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for g in REPORTED:
        for label, rs in (
            ("shipped " + key(SHIPPED), by_set[key(SHIPPED)]),
            ("nested choice", nested),
        ):
            rg = [r for r in rs if r["group"] == g]
            if rg:
                out.append(group_line(g, label, rg))
    out += ["", "nested choice against the shipped cut, paired (the same cases):", ""]
    out += paired(nested, by_set[key(SHIPPED)])
    return "\n".join(out)


def grid_table(by_set: dict[str, list[dict]]) -> str:
    """Every setting on every case (not a held-out figure: the grid the folds chose from)."""
    out = [
        "| setting | BraTS FLAIR 3-D Dice | within 10 % / beyond 25 % | LGG per-slice Dice | "
        "LGG recall / spec. | LGG 3-D Dice | LGG within 10 % / beyond 25 % | phantom 3-D Dice |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for n, rs in by_set.items():
        g = {k: [r for r in rs if r["group"] == k] for k in REPORTED}

        def m(k, f, g=g):
            return float(np.nanmean([r[f] for r in g[k]])) if g[k] else float("nan")

        def wb(k, g=g):
            e = np.abs([r["vol_err"] for r in g[k]])
            return f"{int(np.sum(e <= 10))} / {int(np.sum(e > 25))}"

        out.append(
            f"| {n} | {m('brats_flair', 'dice3d'):.3f} | {wb('brats_flair')} | "
            f"{m('lgg', 'slice_dice'):.3f} | {m('lgg', 'recall'):.3f} / {m('lgg', 'spec'):.3f} | "
            f"{m('lgg', 'dice3d'):.3f} | {wb('lgg')} | {m('phantom', 'dice3d'):.3f} |"
        )
    return "\n".join(out)


def add_scoring_arguments(ap: argparse.ArgumentParser) -> None:
    """The options of a script that scores settings on a saved run's maps (and this one's)."""
    ap.add_argument("--rows-in", help="the shipped run's learned_cv.py --json rows (folds)")
    ap.add_argument("--prob", help="the run's --save-prob folder")
    ap.add_argument("--cache", help="learned_cv.py's prepared-case cache")
    ap.add_argument("--config", default=str(ROOT / "configs" / "default.yaml"))
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument("--scored", required=True, help="every setting's rows (JSON): read if there")


def scored_settings(args, score) -> dict[str, list[dict]]:
    """Every setting's rows: read from ``--scored`` if there, else ``score(rows_in, prob_dir,
    cache, cfg)`` of the saved run, written there."""
    if Path(args.scored).is_file():
        return json.loads(Path(args.scored).read_text())
    from tumor3d.config import parse_config

    cfg = parse_config(Path(args.config).read_text(), source=args.config)
    rows_in = json.loads(Path(args.rows_in).read_text())
    by_set = score(rows_in, Path(args.prob), args.cache, cfg)
    Path(args.scored).write_text(json.dumps(by_set, indent=1))
    return by_set


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_scoring_arguments(ap)
    ap.add_argument("--objective", choices=("targets", "pooled3d"), default="targets")
    args = ap.parse_args(argv)
    folds = list(range(args.folds))
    by_set = scored_settings(args, score_settings)
    print(report(by_set, folds, args.objective))
    print()
    print(grid_table(by_set))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
