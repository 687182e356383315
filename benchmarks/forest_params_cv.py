"""Nested choice of the FLAIR + T2 forest's LightGBM parameters (issue 28).

``tumor3d.learned.training.TRAIN_PARAMS`` (150 trees of at most 31 leaves, learning rate
0.08, 200 rows per leaf) were set once and never chosen by cross-validation. This
scores a small grid, fixed before any fold was scored (:data:`GRID`), for the forest that
segments FLAIR and T2 (``hyper``; the T1c forest is left as it is):

* every setting is trained, in each of the 5 folds of ``learned_cv.py``, on the same
  sampled rows of the other folds' cases (``learned_cv._training_rows``: rows seeded 0, or
  ``--forest-seed``), with the shipped parameters otherwise;
* each held-out FLAIR case is cut as the shipped method cuts it: the mean of the forest's
  probability and the saved out-of-fold U-Net ensemble's (``--prob``: a ``learned_cv.py
  --cnn-folds ... --save-prob`` run's maps, key ``cnn``) above 0.5, its main region
  (keep fraction 1.0), ``segment.min_tumor_pixels``; T2 cases (and the T2 phantoms) with
  the forest alone; scored by ``learned_cv.score``.

The shipped setting must give the run's own lesions back (the saved maps are float16:
printed as the largest relative volume difference). The choice is
``cut_select.nested_choice`` with its objective (0.5 BraTS FLAIR 3-D Dice + 0.5 LGG
per-slice Dice): for outer fold k, the setting best on the other folds' rows.

Usage (``reports/learned_cv.md``, "The forest's parameters, nested")::

    TUMOR3D_DATA_DIR=../shared/data nice -n 10 python benchmarks/forest_params_cv.py \\
        --rows-in learned.json --prob prob --cache /tmp/cv-cache --scored params_rows.json

``--scored`` keeps every setting's rows: a second run with the same file only selects.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from cnn_select import group_line  # noqa: E402
from cut_select import nested_choice, paired  # noqa: E402

#: name -> (LightGBM parameters over TRAIN_PARAMS, boosting rounds); the shipped one first
GRID: dict[str, tuple[dict, int]] = {
    "shipped": ({"learning_rate": 0.08, "num_leaves": 31, "min_data_in_leaf": 200}, 150),
    "deeper": ({"learning_rate": 0.08, "num_leaves": 63, "min_data_in_leaf": 100}, 150),
    "longer": ({"learning_rate": 0.04, "num_leaves": 31, "min_data_in_leaf": 200}, 400),
    "shallow": ({"learning_rate": 0.08, "num_leaves": 15, "min_data_in_leaf": 400}, 150),
}
REPORTED = ("brats_flair", "lgg", "brats_t2", "phantom")


def score_grid(args, cfg) -> dict[str, list[dict]]:
    """Every setting's out-of-fold rows of the FLAIR and T2 cases of ``--rows-in``."""
    import learned_cv as L

    from tumor3d.learned.training import TrainingRows, train_forest
    from tumor3d.storage.manifest import data_dir

    rows_in = [r for r in json.loads(Path(args.rows_in).read_text())]
    n_ph = sum(r["case"].startswith("phantom/") for r in rows_in) // 2
    specs = L.case_specs(data_dir()) + L.phantom_specs(n_ph)
    preps = [L.cached_prepare(s, cfg, True, args.cache) for s in specs]
    folds = L.assign_folds(specs, args.folds)
    fold_in = {r["case"]: r["fold"] for r in rows_in}
    for p in preps:  # the saved run's folds are these
        if p.spec.name in fold_in and fold_in[p.spec.name] != folds[p.spec.patient]:
            raise SystemExit(f"{p.spec.name}: fold {folds[p.spec.patient]} here, "
                             f"{fold_in[p.spec.name]} in {args.rows_in}")  # fmt: skip
    ns = SimpleNamespace(forest_seed=args.forest_seed, train_offsets=[L.OFFSET])
    t0 = time.perf_counter()
    rows_of = L._training_rows(preps, ns, cfg)
    print(f"sampled rows in {time.perf_counter() - t0:.0f} s", flush=True)
    mods = dict(L.FAMILIES)["hyper"]
    run = {r["case"]: r for r in rows_in}
    cut = SimpleNamespace(threshold=args.threshold, t1c_threshold=None, keep_fraction=1.0)
    out: dict[str, list[dict]] = {n: [] for n in GRID}
    worst = 0.0
    for k in range(args.folds):
        train = [p for p in preps if folds[p.spec.patient] != k and p.spec.modality in mods]
        held = [
            p
            for p in preps
            if folds[p.spec.patient] == k and p.spec.modality in mods and p.spec.name in run
        ]
        rows = TrainingRows.concatenate([rows_of[p.spec.name] for p in train])
        for name, (params, rounds) in GRID.items():
            t1 = time.perf_counter()
            if args.forest_seed is not None:
                params = {**params, "seed": int(args.forest_seed)}
            model = train_forest(rows, params=params, num_rounds=rounds)
            for p in held:
                forest = L.forest_probability(p, model)
                prob = forest
                with np.load(L.case_file(args.prob, p.spec.name)) as z:
                    if "cnn" in z.files:  # FLAIR: the mean with the fold's U-Net ensemble
                        prob = (0.5 * forest + 0.5 * z["cnn"].astype(np.float32)).astype(np.float32)
                mask = L._final_mask(p, prob, cut, cfg)  # as shipped: main region
                row = L.score(p, mask, cfg)
                row["fold"] = k
                out[name].append(row)
                if name == "shipped" and args.forest_seed is None:
                    r0 = run[p.spec.name]
                    worst = max(worst, abs(row["est_ml"] - r0["est_ml"]) / max(r0["est_ml"], 1e-9))
            print(f"fold {k} {name}: {len(rows.y)} rows, {len(held)} cases, "
                  f"{time.perf_counter() - t1:.0f} s", flush=True)  # fmt: skip
    if args.forest_seed is None:
        print(f"shipped setting's lesions within {worst:.2%} of the run's volumes", flush=True)
    return out


def report(by_set: dict[str, list[dict]], folds: list[int]) -> str:
    choice, inner = nested_choice(by_set, folds, "targets")
    nested = [r for k in folds for r in by_set[choice[k]] if r["fold"] == k]
    out = ["objective: 0.5 BraTS FLAIR 3-D Dice + 0.5 LGG per-slice Dice", "",
           "| outer fold | chosen | objective on the other folds (chosen / shipped) |",
           "|---|---|---|"]  # fmt: skip
    for k in folds:
        c, s = inner[k][choice[k]], inner[k]["shipped"]
        out.append(f"| {k} | {choice[k]} | {c[0]:.4f} / {s[0]:.4f} |")
    counts = {n: sum(c == n for c in choice.values()) for n in by_set}
    out += ["", "chosen: " + ", ".join(f"{n} in {c} of {len(folds)}" for n, c in counts.items()
                                       if c)]  # fmt: skip
    out += ["", "| group | setting | n | 3-D Dice mean ± sd (median) | per-slice Dice | slice "
            "recall / spec. | volume error mean abs (median) | within 10 % / beyond 25 % |",
            "|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for g in REPORTED:
        for label, rs in [("nested choice", nested), *by_set.items()]:
            rg = [r for r in rs if r["group"] == g]
            if rg:
                out.append(group_line(g, label, rg))
    out += ["", "nested choice against shipped, paired (the same cases):", ""]
    out += paired(nested, by_set["shipped"], REPORTED, wilcoxon_p=True)
    return "\n".join(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows-in", help="the shipped run's learned_cv.py --json rows (folds)")
    ap.add_argument("--prob", help="the run's --save-prob folder (key cnn: the U-Net's map)")
    ap.add_argument("--cache", help="learned_cv.py's prepared-case cache")
    ap.add_argument("--config", default=str(ROOT / "configs" / "default.yaml"))
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument("--threshold", type=float, default=0.5)
    ap.add_argument("--forest-seed", type=int, default=None, help="as learned_cv.py's")
    ap.add_argument("--scored", required=True, help="every setting's rows (JSON): read if there")
    args = ap.parse_args(argv)
    if Path(args.scored).is_file():
        by_set = json.loads(Path(args.scored).read_text())
    else:
        from tumor3d.config import parse_config

        cfg = parse_config(Path(args.config).read_text(), source=args.config)
        by_set = score_grid(args, cfg)
        Path(args.scored).write_text(json.dumps(by_set, indent=1))
    print(report(by_set, list(range(args.folds))))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
