"""Nested choice of a hysteresis growth of the learned lesion into its margin (issue 28).

The learned method's misses are mostly under-segmentations: on the LGG heads and
BraTS cases whose volume is short by 30-70 %, a quarter to a third of the missed
tumour voxels have a probability of 0.3-0.5, just under the cut (0.5), and lie
against the lesion that was found. A lower global cut finds them but also new
regions elsewhere ("The mean's cut ... nested": specificity and volumes lost).
Hysteresis (Canny 1986) keeps the cut for *where* the lesion is and a lower one for
*how far* it reaches: the lesion cut at 0.5 (:func:`keep_main_lesion`) grows into
the voxels above ``low`` connected to it, and nothing that does not touch it is added.

A grid fixed before any fold was scored, on the saved out-of-fold maps of the shipped
run (``learned_cv.py --cnn-folds ... --save-prob``; key ``prob``, the map the
pipeline cut):

* ``low`` in {none (shipped), 0.4, 0.3, 0.2};
* the growth 26-connected in 3-D (it may reach slices the cut missed), or in-plane
  only (8-connected, inside the slices the lesion already has; a slice mask under
  ``segment.min_tumor_pixels``, cleared after the growth as before it, may grow past
  that limit and be kept, so the slices found can still change a little).

Two families, chosen apart (their maps differ): FLAIR (forest + U-Net mean; the
objective of ``cut_select.py``: 0.5 BraTS FLAIR 3-D Dice + 0.5 LGG per-slice Dice)
and the forest alone (BraTS T2 and T1c; objective: mean 3-D Dice of the two groups,
each weighing the same). Ties: the lower mean absolute volume error, then the grid
order (shipped first). Nested by patient on the run's 5 folds, as ``cut_select.py``.

Usage::

    TUMOR3D_DATA_DIR=../shared/data python benchmarks/grow_select.py \\
        --rows-in learned.json --prob prob --cache /tmp/cv-cache --scored grow_rows.json
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy import ndimage as ndi

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from cnn_select import group_line  # noqa: E402  (the same table row)
from cut_select import add_scoring_arguments, nested_choice, paired, scored_settings  # noqa: E402

from tumor3d.imaging.preprocess import fill_holes_per_slice  # noqa: E402

LOWS = (None, 0.4, 0.3, 0.2)  # None: the shipped lesion
MODES = ("3d", "2d")
SETTINGS = ((None, "-"),) + tuple((lo, m) for lo in LOWS[1:] for m in MODES)
SHIPPED = "shipped"
FAMILIES = {
    "flair": {"groups": ("brats_flair", "lgg"), "reported": ("brats_flair", "lgg", "phantom")},
    "forest": {"groups": ("brats_t2", "brats_t1c"), "reported": ("brats_t2", "brats_t1c")},
}


def key(s) -> str:
    return SHIPPED if s[0] is None else f"low={s[0]:g} {s[1]}"


def grow(mask: np.ndarray, prob: np.ndarray, low: float, mode: str) -> np.ndarray:
    """``mask`` and every voxel above ``low`` connected to it (3-D, or in-plane only).

    >>> p = np.zeros((2, 6, 6), np.float32); p[0, 1:3, 1:3] = 0.9; p[0, 3, 1:3] = 0.35
    >>> p[1, 1:3, 1:3] = 0.35; p[0, 5, 5] = 0.35
    >>> m = p > 0.5
    >>> int(grow(m, p, 0.3, "3d").sum()), int(grow(m, p, 0.3, "2d").sum())
    (10, 6)
    """
    above = (prob > low) | mask
    if mode == "3d":
        labels, _ = ndi.label(above, structure=np.ones((3, 3, 3), bool))
        keep = np.unique(labels[mask])
        out = np.isin(labels, keep[keep > 0])
    else:
        out = mask.copy()
        for z in np.flatnonzero(mask.any(axis=(1, 2))):
            labels, _ = ndi.label(above[z], structure=np.ones((3, 3), bool))
            keep = np.unique(labels[mask[z]])
            out[z] = np.isin(labels, keep[keep > 0])
    return fill_holes_per_slice(out)


def family_of(group: str) -> str | None:
    for name, f in FAMILIES.items():
        if group in f["reported"]:
            return name
    return None


def objective(rows: list[dict], family: str) -> tuple[float, float]:
    """(objective, mean abs volume error) of a family's rows."""
    groups = FAMILIES[family]["groups"]
    rs = [r for r in rows if r["group"] in groups]
    err = float(np.nanmean([abs(r["vol_err"]) for r in rs]))
    if family == "flair":
        b = np.nanmean([r["dice3d"] for r in rs if r["group"] == "brats_flair"])
        s = np.nanmean([r["slice_dice"] for r in rs if r["group"] == "lgg"])
        return round(float(0.5 * b + 0.5 * s), 12), err
    per = [np.nanmean([r["dice3d"] for r in rs if r["group"] == g]) for g in groups]
    return round(float(np.mean(per)), 12), err


def score_settings(rows_in, prob_dir: Path, cache: str, cfg) -> dict[str, list[dict]]:
    import learned_cv as L

    from tumor3d.learned.segment import keep_main_lesion
    from tumor3d.storage.manifest import data_dir

    n_ph = sum(r["case"].startswith("phantom/") for r in rows_in) // 2
    specs = {s.name: s for s in L.case_specs(data_dir()) + L.phantom_specs(n_ph)}
    out: dict[str, list[dict]] = {key(s): [] for s in SETTINGS}
    worst = 0.0
    for r in rows_in:
        fam = family_of(r["group"])
        if fam is None or (r["group"] == "phantom" and not r["case"].endswith("/flair")):
            continue
        with np.load(L.case_file(prob_dir, r["case"])) as z:
            prob = z["prob"].astype(np.float32)
        p = L.cached_prepare(specs[r["case"]], cfg, True, cache)
        thr = 0.65 if r["group"] == "brats_t1c" else 0.5  # the shipped cuts
        base = keep_main_lesion(prob, thr, keep_fraction=1.0, min_voxels=L._min_voxels(p))
        for s in SETTINGS:
            mask = base.copy() if s[0] is None else grow(base, prob, s[0], s[1])
            mask[mask.sum(axis=(1, 2)) < cfg.segment.min_tumor_pixels] = False
            row = L.score(p, mask, cfg)
            row["fold"] = r["fold"]
            out[key(s)].append(row)
            if s[0] is None:
                worst = max(worst, abs(row["est_ml"] - r["est_ml"]) / max(r["est_ml"], 1e-9))
        print(f"  {r['case']}", flush=True)
    print(f"shipped setting's lesions within {worst:.2%} of the run's volumes", flush=True)
    return out


def report(by_set: dict[str, list[dict]], folds: list[int], family: str) -> str:
    reported = FAMILIES[family]["reported"]
    fam = {n: [r for r in rs if r["group"] in reported] for n, rs in by_set.items()}
    choice, inner = nested_choice(fam, folds, family, objective)
    nested = [r for k in folds for r in fam[choice[k]] if r["fold"] == k]
    counts = {n: sum(c == n for c in choice.values()) for n in fam}
    out = [f"family: {family}", "", "| outer fold | chosen | objective on the other folds "
           "(chosen / shipped) |", "|---|---|---|"]  # fmt: skip
    for k in folds:
        c, s = inner[k][choice[k]], inner[k][SHIPPED]
        out.append(f"| {k} | {choice[k]} | {c[0]:.4f} / {s[0]:.4f} |")
    chosen = ", ".join(f"{n} in {c} of {len(folds)}" for n, c in counts.items() if c)
    out += ["", "chosen: " + chosen]
    out += [
        "",
        "| group | lesion | n | 3-D Dice mean ± sd (median) | per-slice Dice | slice recall / "
        "spec. | volume error mean abs (median) | within 10 % / beyond 25 % |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for g in reported:
        for label, rs in (("shipped", fam[SHIPPED]), ("nested choice", nested)):
            rg = [r for r in rs if r["group"] == g]
            if rg:
                out.append(group_line(g, label, rg))
    out += ["", "nested choice against the shipped lesion, paired (Wilcoxon p):", ""]
    out += paired(nested, fam[SHIPPED], reported, wilcoxon_p=True)
    out += ["", "every setting on every case (the grid the folds chose from):", ""]
    heads = " | ".join(f"{g} 3-D / per-slice / spec / abs vol err" for g in reported)
    out += [f"| setting | {heads} |", "|---" * (len(reported) + 1) + "|"]
    for n, rs in fam.items():
        cells = []
        for g in reported:
            rg = [r for r in rs if r["group"] == g]
            cells.append(
                f"{np.nanmean([r['dice3d'] for r in rg]):.3f} / "
                f"{np.nanmean([r['slice_dice'] for r in rg]):.3f} / "
                f"{np.nanmean([r['spec'] for r in rg]):.3f} / "
                f"{np.nanmean([abs(r['vol_err']) for r in rg]):.1f} %"
            )
        out.append(f"| {n} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def gated(by_set: dict[str, list[dict]], gates) -> dict[str, list[dict]]:
    """The shipped lesion and, per growth setting and gate ``r``: a case grown only when
    growth would enlarge its lesion by more than ``r`` (a figure of its own maps; the
    under-segmented lesions grow most), else the shipped lesion.

    >>> row = lambda c, ml: {"case": c, "est_ml": ml}
    >>> by = {SHIPPED: [row("a", 10.0), row("b", 10.0)], "g": [row("a", 11.0), row("b", 14.0)]}
    >>> [r["est_ml"] for r in gated(by, [0.2])["g gate>0.2"]]
    [10.0, 14.0]
    """
    base = {r["case"]: r for r in by_set[SHIPPED]}
    out = {SHIPPED: by_set[SHIPPED]}
    for name, rows in by_set.items():
        if name == SHIPPED:
            continue
        for r_gate in gates:
            out[f"{name} gate>{r_gate:g}"] = [
                r if r["est_ml"] > (1.0 + r_gate) * base[r["case"]]["est_ml"] else base[r["case"]]
                for r in rows
            ]
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_scoring_arguments(ap)
    ap.add_argument(
        "--gates", type=float, nargs="+", help="choose among gated growths instead (gated())"
    )
    args = ap.parse_args(argv)
    folds = list(range(args.folds))
    by_set = scored_settings(args, score_settings)
    if args.gates:
        by_set = gated(by_set, args.gates)
    for family in FAMILIES:
        print(report(by_set, folds, family))
        print()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
