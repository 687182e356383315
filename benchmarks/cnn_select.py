"""Nested choice among the forest, the U-Net and the mean of the two (issue 28).

The three candidates and the mean's equal weights were fixed before any fold
was scored (``benchmarks/cnn_cv.py``); the choice among them is the nested
step made here. For each outer fold k the candidate with the highest mean 3-D
Dice over the OTHER folds' out-of-fold FLAIR cases (LGG heads and BraTS FLAIR
slabs pooled; tie-break: the lower mean absolute volume error, then the order
forest, U-Net, mean) is chosen, and fold k is scored with it. Every candidate's
row of a case is out of fold (its model never saw that patient); the rows of
the other folds that make the choice come from models that did see fold k's
patients in training (a fully nested choice would retrain every inner net: not
done).

Scoring as ``cnn_cv.py`` (:func:`cnn_cv.score_folds`: threshold 0.5, the main
3-D region, small slice masks cleared, :func:`learned_cv.score`), so the rows
are those of the tables in ``reports/learned_cv.md``.

Usage (the subsection "Nested choice" of ``reports/learned_cv.md``)::

    TUMOR3D_DATA_DIR=../shared/data nice -n 10 python benchmarks/cnn_select.py \\
        --cache /tmp/cv-cache --work /tmp/cnn --forest-prob prob --forest-key prob1 \\
        --rows select_rows.json

``--work`` is ``cnn_cv.py``'s folder (``data.npz``, ``prob_fold{k}.npz``),
``--forest-prob`` the shipped model's ``--save-prob`` folder of the same folds.
``--rows`` keeps the scored rows: a second run with the same file only selects.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
CANDIDATES = ("forest", "U-Net", "mean")  # fixed before any fold was scored
GROUPS = ("lgg", "brats_flair")


def candidate_score(rows: list[dict]) -> tuple[float, float]:
    """(mean 3-D Dice, mean absolute volume error %) of ``rows``."""
    return (
        float(np.nanmean([r["dice3d"] for r in rows])),
        float(np.nanmean([abs(r["vol_err"]) for r in rows])),
    )


def nested_choice(by_cand: dict[str, list[dict]], folds: list[int]):
    """Per outer fold: the candidate chosen on the other folds, and the inner scores.

    Returns ``(choice, inner)``: ``choice[k]`` a name of :data:`CANDIDATES`,
    ``inner[k][name]`` its (mean 3-D Dice, mean abs volume error) on the other
    folds' cases.

    >>> r = lambda f, d, v: {"fold": f, "dice3d": d, "vol_err": v}
    >>> c = {"forest": [r(0, 0.9, 5), r(1, 0.1, 5)], "U-Net": [r(0, 0.2, 5), r(1, 0.8, 5)],
    ...      "mean": [r(0, 0.5, 5), r(1, 0.5, 5)]}
    >>> nested_choice(c, [0, 1])[0]
    {0: 'U-Net', 1: 'forest'}
    """
    choice, inner = {}, {}
    for k in folds:
        inner[k] = {
            name: candidate_score([r for r in by_cand[name] if r["fold"] != k])
            for name in CANDIDATES
        }
        # highest Dice; then lowest volume error; then the fixed order
        choice[k] = min(
            CANDIDATES,
            key=lambda n: (-inner[k][n][0], inner[k][n][1], CANDIDATES.index(n)),  # noqa: B023
        )
    return choice, inner


def group_line(g: str, label: str, rs: list[dict]) -> str:
    a = {k: np.array([r[k] for r in rs], float) for k in ("slice_dice", "recall", "spec", "dice3d")}
    ve = np.array([r["vol_err"] for r in rs], float)
    err = np.abs(ve)
    return (
        f"| {g} | {label} | {len(rs)} | {np.nanmean(a['dice3d']):.3f} ± "
        f"{np.nanstd(a['dice3d']):.3f} ({np.nanmedian(a['dice3d']):.3f}) | "
        f"{np.nanmean(a['slice_dice']):.3f} ± {np.nanstd(a['slice_dice']):.3f} | "
        f"{np.nanmean(a['recall']):.3f} / {np.nanmean(a['spec']):.3f} | "
        f"{np.nanmean(err):.1f} % ({np.nanmedian(ve):+.1f} %) | "
        f"{int(np.sum(err <= 10))} / {int(np.sum(err > 25))} |"
    )


def report(by_cand: dict[str, list[dict]], folds: list[int]) -> str:
    from cnn_cv import paired_table

    choice, inner = nested_choice(by_cand, folds)
    nested = [
        r for k in folds for r in by_cand[choice[k]] if r["fold"] == k and r["group"] in GROUPS
    ]
    out = [
        "| outer fold | chosen | "
        + " | ".join(f"{n}: 3-D Dice / abs. vol. err. on the other folds" for n in CANDIDATES)
        + " |",
        "|---|---|" + "---|" * len(CANDIDATES),
    ]
    for k in folds:
        out.append(
            f"| {k} | {choice[k]} | "
            + " | ".join(f"{inner[k][n][0]:.3f} / {inner[k][n][1]:.1f} %" for n in CANDIDATES)
            + " |"
        )
    out += [
        "",
        "| group | model | n | 3-D Dice mean ± sd (median) | per-slice Dice | slice recall / "
        "spec. | volume error mean abs (median) | within 10 % / beyond 25 % |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for g in GROUPS:
        for label, rs in (
            ("shipped forest", by_cand["forest"]),
            ("U-Net", by_cand["U-Net"]),
            ("mean of the two", by_cand["mean"]),
            ("nested choice", nested),
        ):
            rg = [r for r in rs if r["group"] == g and r["fold"] in folds]
            if rg:
                out.append(group_line(g, label, rg))
    out += ["", "nested choice against the shipped forest, paired:", ""]
    out.append(paired_table(nested, by_cand["forest"], "shipped forest", "nested choice"))
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "default.yaml"))
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument("--cache", default=None, help="learned_cv.py's preparation cache")
    ap.add_argument("--work", default="/tmp/cnn-cv", help="cnn_cv.py's folder")
    ap.add_argument("--forest-prob", default=None, help="the shipped model's --save-prob folder")
    ap.add_argument("--forest-key", default="prob")
    ap.add_argument("--threshold", type=float, default=0.5)
    ap.add_argument("--keep-fraction", type=float, default=1.0)
    ap.add_argument(
        "--mirror",
        action="store_true",
        help="the U-Net as the pipeline runs it (cnn_cv.py --mirror: with its mirrored pass)",
    )
    ap.add_argument(
        "--rows", default=None, help="the scored rows (JSON): read if there, else written"
    )
    args = ap.parse_args(argv)
    sys.path.insert(0, str(ROOT))
    sys.path.insert(0, str(ROOT / "benchmarks"))
    folds = list(range(args.folds))
    if args.rows and Path(args.rows).is_file():
        by_cand = json.loads(Path(args.rows).read_text())
    else:
        import learned_cv as L
        from cnn_cv import score_folds

        from tumor3d.config import parse_config
        from tumor3d.storage.manifest import data_dir

        data = data_dir()
        if not data.is_dir():
            print(f"skipped: no real data at {data} (set TUMOR3D_DATA_DIR)")
            return 0
        if not args.forest_prob:
            raise SystemExit("--forest-prob is needed to score the candidates")
        cfg = parse_config(Path(args.config).read_text(), source=args.config)
        specs = L.case_specs(data)
        fold_of = L.assign_folds(specs, args.folds)  # on every case, as learned_cv.py
        specs = [s for s in specs if s.group in GROUPS]
        preps = [L.cached_prepare(s, cfg, False, args.cache) for s in specs]
        with np.load(Path(args.work) / "data.npz", allow_pickle=False) as z:
            case_of, train_only = z["case"], z["train_only"]
            if "names" in z.files and list(z["names"]) != [p.spec.name for p in preps]:
                raise SystemExit(f"{args.work}/data.npz holds other cases")
        unet, forest, mean = score_folds(preps, fold_of, folds, case_of, train_only, args, cfg)
        by_cand = {"forest": forest, "U-Net": unet, "mean": mean}
        if args.rows:
            Path(args.rows).write_text(json.dumps(by_cand, indent=1))
    print(report(by_cand, folds))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
