"""Interpolation on reference labels: Table 4 of the paper and the every-k-th-slice protocol.

Runs :func:`tumor3d.evaluation.interpolation.table4_rows` and
:func:`~tumor3d.evaluation.interpolation.kth_slice_rows` on

* phantoms with a drifting, lobed tumour (``drifting_tumour_phantom``, seeds 0-4);
* the real labelled cases in ``$TUMOR3D_DATA_DIR`` (default ``../shared/data``):
  BraTS 2013 patients 3, 4, 5 (expert labels, whole tumour = label > 0) and
  ``brats_t2_algoseg`` (an algorithm's label, reported separately);

and writes ``reports/interpolation.md`` (with the speed figures of
``benchmarks/bench_interpolate.py`` unless ``--no-bench``).

    PYTHONPATH=. python benchmarks/interpolation_eval.py            # full run (~15 min)
    PYTHONPATH=. python benchmarks/interpolation_eval.py --phases 1 # phase 0 only
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from tumor3d.evaluation.interpolation import (
    ITK_METHOD,
    drifting_tumour_phantom,
    itk_available,
    kth_slice_rows,
    table4_rows,
)
from tumor3d.geometry.interpolate.methods import _DEFAULT_METHOD, _DEFAULT_PARTS
from tumor3d.storage.manifest import data_dir

ROOT = Path(__file__).resolve().parents[1]
EXPERT = ["brats2013_pat0003", "brats2013_pat0004", "brats2013_pat0005"]
ALGO = ["brats_t2_algoseg"]
TABLE4_METHODS = ["LG", "SO", "SE", "SE-EDT", "SE-EDT parts", "SO-EDT", "SO-EDT parts"]
FLUSH_METHODS = ["SO", "SE", "SO-EDT", "SO-EDT parts"]
KTH_METHODS = ["LG", "SO", "SE", "SE-EDT", "SE-EDT parts", "SO-EDT", "SO-EDT parts"]
LABEL_OF = {
    ("linear", "whole"): "LG",
    ("shape", "whole"): "SO",
    ("enhanced", "whole"): "SE",
    ("enhanced-edt", "whole"): "SE-EDT",
    ("enhanced", "matched"): "SE parts",
    ("enhanced-edt", "matched"): "SE-EDT parts",
    ("shape-edt", "whole"): "SO-EDT",
    ("shape-edt", "matched"): "SO-EDT parts",
}
DEFAULT_LABEL = LABEL_OF[(_DEFAULT_METHOD, _DEFAULT_PARTS)]





def load_label(case: str) -> np.ndarray | None:
    """Whole-tumour label as a (z, y, x) bool array, or None when absent."""
    import nibabel as nib

    name = "seg_algorithm.nii.gz" if case.startswith("brats_t2") else "seg.nii.gz"
    path = data_dir() / case / name
    if not path.exists():
        return None
    img = nib.load(path)
    zooms = img.header.get_zooms()[:3]
    if not np.allclose(zooms, 1.0):
        raise SystemExit(f"{path}: expected 1 mm voxels, got {zooms}")
    lab = np.asarray(img.dataobj).astype(np.int64) > 0  # (x, y, z)
    return np.ascontiguousarray(np.transpose(lab, (2, 1, 0)))


def md_table(df: pd.DataFrame, floatfmt: str = "{:.2f}") -> str:
    cols = [str(c) for c in df.columns]
    head = "| " + " | ".join([df.index.name or ""] + cols) + " |"
    sep = "|" + "---|" + "---:|" * len(cols)
    lines = [head, sep]
    for idx, row in df.iterrows():
        cells = [floatfmt.format(v) if isinstance(v, float) else str(v) for v in row]
        lines.append("| " + " | ".join([str(idx)] + cells) + " |")
    return "\n".join(lines)


def table4_section(rows: list[dict], cases: list[str], methods: list[str]) -> str:
    df = pd.DataFrame(rows)
    out = []
    means = {}
    for case in cases:
        sub = df[df.case == case]
        if sub.empty:
            continue
        piv = sub.pivot_table(index="slices", columns="method", values="epsilon_percent")
        piv = piv[[m for m in methods if m in piv.columns]]
        piv = piv.loc[sorted(piv.index, key=lambda s: int(s.split("-")[0]))]
        piv.index.name = "Slices"
        means[case] = piv.mean()
        out.append(f"**{case}** ({len(piv)} triplets)\n\n{md_table(piv)}\n")
    mean_df = pd.DataFrame(means).T
    mean_df.index.name = "case: mean epsilon %"
    return md_table(mean_df) + "\n\n" + "\n".join(out)


def kth_summary(rows: list[dict]) -> pd.DataFrame:
    df = pd.DataFrame(rows)
    df["label"] = df.method + np.where(df.end_caps == "none", " (flat caps)", "")
    return df.groupby(["case", "k", "label"], sort=False)[
        ["dice", "hd95_mm", "volume_error_percent"]
    ].mean()


def kth_section(rows: list[dict], cases: list[str]) -> str:
    summ = kth_summary(rows).reset_index()
    out = []
    for k in sorted(summ.k.unique()):
        sub = summ[summ.k == k]
        for value, name, fmt in (
            ("dice", "3-D Dice", "{:.4f}"),
            ("hd95_mm", "HD95 (mm)", "{:.2f}"),
            ("volume_error_percent", "volume error (%)", "{:+.2f}"),
        ):
            piv = sub.pivot_table(index="label", columns="case", values=value, sort=False)
            piv = piv[[c for c in cases if c in piv.columns]]
            piv.index.name = f"k = {k}: {name}"
            out.append(md_table(piv, fmt) + "\n")
    return "\n".join(out)


def _pick(df: pd.DataFrame) -> tuple[str, list[str]]:
    """Best mean Dice; ties (within 2 paired standard errors) go to the smallest |vol. err|.

    ``df`` holds the k = 5, taper rows of some cases; pairs are (case, phase).
    """
    dice = df.pivot_table(index=["case", "phase"], columns="method", values="dice")
    vol = df.pivot_table(index=["case", "phase"], columns="method", values="volume_error_percent")
    best = str(dice.mean().idxmax())
    tied = []
    for m in dice.columns:
        diff = dice[best] - dice[m]
        se = float(diff.std(ddof=1) / np.sqrt(len(diff))) if len(diff) > 1 else 0.0
        if float(diff.mean()) <= 2.0 * se:
            tied.append(str(m))
    pick = min(tied, key=lambda m: float(vol[m].abs().mean()))
    return pick, tied


def choose_default(rows: list[dict], k: int = 5) -> tuple[str, list[str]]:
    """Apply :func:`_pick` to the expert cases at step k, then leave one case out."""
    df = pd.DataFrame(rows)
    df = df[(df.k == k) & (df.end_caps == "taper") & df.case.isin(EXPERT)]
    dice = df.groupby(["method", "case"]).dice.mean().unstack()
    pick, tied = _pick(df)
    lines = [
        f"all three: best mean Dice {dice.mean(axis=1).idxmax()}; tied within 2 paired "
        f"standard errors: {', '.join(tied)}; smallest mean |volume error| among them: {pick}"
    ]
    for held in dice.columns:
        p, _ = _pick(df[df.case != held])
        lines.append(
            f"without {held}: {p} (Dice on {held}: {dice.loc[p, held]:.4f}; best there "
            f"{dice[held].max():.4f} by {dice[held].idxmax()})"
        )
    return pick, lines


def targets_section(
    t4_ph: list[dict], t4_real: list[dict], kth_real: list[dict], flush_real: list[dict]
) -> str:
    """The issue's targets, checked on the numbers above."""
    out = ["## Targets (issue 8)", ""]
    ph = pd.DataFrame(t4_ph).groupby("method").epsilon_percent.mean()
    ok = ph["SE"] < ph["SO"] < ph["LG"]
    out.append(
        f"- Phantoms, Table 4 protocol, mean epsilon over all triplets: SE {ph['SE']:.2f} %, "
        f"SO {ph['SO']:.2f} %, LG {ph['LG']:.2f} %: SE < SO < LG "
        + ("holds." if ok else "does NOT hold.")
    )
    if t4_real:
        re = pd.DataFrame(t4_real)
        re = re[re.case.isin(EXPERT)].groupby("method").epsilon_percent.mean()
        order = " < ".join(m for m in re[["LG", "SO", "SE"]].sort_values().index)
        out.append(
            f"- Real expert labels, same protocol: SE {re['SE']:.2f} %, SO {re['SO']:.2f} %, "
            f"LG {re['LG']:.2f} % ({order}): "
            + (
                "the paper's order holds."
                if re["SE"] < re["SO"] < re["LG"]
                else "the real data disagree with the paper: centroid alignment (whole "
                "slice, or per part in SE-EDT parts) does not help on these real tumours."
            )
        )
    if kth_real:
        df = pd.DataFrame(kth_real)
        df = df[df.k == 5]
        dflt = df[(df.method == DEFAULT_LABEL) & (df.end_caps == "taper")]
        dflt = dflt.groupby("case")[["dice", "volume_error_percent"]].mean()
        itk = df[df.method == ITK_METHOD].groupby("case").dice.mean()
        for case, row in dflt.iterrows():
            parts = [
                f"default Dice {row.dice:.4f} ("
                + ("meets" if row.dice >= 0.95 else "BELOW")
                + " 0.95)",
                f"volume error {row.volume_error_percent:+.2f} % ("
                + ("within" if abs(row.volume_error_percent) <= 3.0 else "OUTSIDE")
                + " 3 %)",
            ]
            if case in itk.index:
                parts.append(
                    f"ITK Dice {itk[case]:.4f} (default "
                    + ("higher" if row.dice > itk[case] else "NOT higher")
                    + ")"
                )
            out.append(f"- k = 5, {case}: " + "; ".join(parts) + ".")
    if flush_real:
        df = pd.DataFrame(flush_real)
        mean = df.groupby(["case", "method"])[["dice", "volume_error_percent"]].mean()
        for case in df.case.unique():
            d = mean.loc[(case, DEFAULT_LABEL)]
            txt = f"default Dice {d.dice:.4f}, volume error {d.volume_error_percent:+.2f} %"
            if (case, ITK_METHOD) in mean.index:
                txt += f"; ITK Dice {mean.loc[(case, ITK_METHOD)].dice:.4f}"
            out.append(f"- k = 5, flush slabs (the evaluation flow's emulation), {case}: {txt}.")
    return "\n".join(out) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--phases", type=int, default=0, help="phases per k (0 = all k)")
    parser.add_argument("--seeds", type=int, default=5, help="number of phantom seeds")
    parser.add_argument("--no-bench", action="store_true", help="skip the speed benchmark")
    parser.add_argument("--out", type=Path, default=ROOT / "reports" / "interpolation.md")
    args = parser.parse_args()
    t_start = time.time()
    have_itk = itk_available()
    if not have_itk:
        print("ITK's MorphologicalContourInterpolator missing: pip install 'tumor3d[peers]'")
    t4_methods = TABLE4_METHODS + ([ITK_METHOD] if have_itk else [])
    kth_methods = KTH_METHODS + ([ITK_METHOD] if have_itk else [])

    def phases(k: int) -> list[int] | None:
        return None if args.phases == 0 else list(range(min(args.phases, k)))

    # phantoms
    t4_ph, kth_ph = [], []
    ph_cases = [f"phantom{s}" for s in range(args.seeds)]
    for seed, case in enumerate(ph_cases):
        lab = drifting_tumour_phantom(seed)
        t4_ph += table4_rows(lab, case=case, methods=t4_methods, include_itk=False)
        for k in (3, 5):
            kth_ph += kth_slice_rows(
                lab,
                case=case,
                steps=(k,),
                phases=phases(k),
                methods=kth_methods,
                include_itk=False,
                end_caps=("taper", "none"),
            )
        print(f"{case}: done ({time.time() - t_start:.0f} s)", flush=True)

    # real cases
    t4_real, kth_real, flush_real, real_cases, missing = [], [], [], [], []
    for case in EXPERT + ALGO:
        lab = load_label(case)
        if lab is None:
            missing.append(case)
            print(f"{case}: not found under {data_dir()} (set TUMOR3D_DATA_DIR), skipped")
            continue
        real_cases.append(case)
        t4_real += table4_rows(lab, case=case, methods=t4_methods, include_itk=False)
        for k in (3, 5):
            kth_real += kth_slice_rows(
                lab,
                case=case,
                steps=(k,),
                phases=phases(k),
                methods=kth_methods,
                include_itk=False,
                end_caps=("taper", "none"),
            )
        flush_real += kth_slice_rows(
            lab,
            case=case,
            steps=(5,),
            phases=phases(5),
            methods=FLUSH_METHODS + ([ITK_METHOD] if have_itk else []),
            include_itk=False,
            end_caps=("taper",),
            slab="flush",
        )
        print(f"{case}: done ({time.time() - t_start:.0f} s)", flush=True)

    lines = [
        "# Inter-slice interpolation on reference labels",
        "",
        "Generated by `PYTHONPATH=. python benchmarks/interpolation_eval.py"
        + (f" --phases {args.phases}" if args.phases else "")
        + "` "
        f"({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {time.time() - t_start:.0f} s). "
        "Methods: LG = linear mask interpolation (mask variant of [A14]); SO = city-block "
        "shape-based; SE = Algorithm 1 (chamfer, one centroid per slice); -EDT = exact "
        "Euclidean distance; parts = matched parts (tumor3d.geometry.interpolate); ITK = ITK's "
        "MorphologicalContourInterpolator"
        + ("" if have_itk else " (NOT INSTALLED: no ITK column)")
        + f". The pipeline default is **{DEFAULT_LABEL}** "
        f"(`method: {_DEFAULT_METHOD}`, `parts: {_DEFAULT_PARTS}`, `end_caps: taper`); "
        "`configs/paper.yaml` is SE with flat caps.",
        "",
        "Thick slices are emulated from the 1 mm labels: slice j is centred on thin slice "
        "phase + j k and covers 2 mm; its label is tumour where the overlap-weighted mean of "
        "the thin labels is >= 0.5 (`emulate_thick_labels`).",
        "",
        "## Table 4 protocol (Eq. 10, S_i and S_i+2 give S_i+1 at t = 1/2)",
        "",
        "On the thick-slice stack at a 5 mm step (the paper's geometry: S_i and S_i+2 are "
        "10 mm apart), every triplet whose three slices hold tumour. Paper (Table 4, its own "
        "data): LG 5.38-11.17, SO 2.93-8.79, SE 2.77-5.03 %.",
        "",
        "### Phantoms with a drifting tumour",
        "",
        table4_section(t4_ph, ph_cases, t4_methods),
        "",
    ]
    if real_cases:
        lines += [
            "### Real labels (BraTS expert; brats_t2_algoseg = algorithm)",
            "",
            table4_section(t4_real, real_cases, t4_methods),
            "",
        ]
    lines += [
        "## Every k-th slice kept, reconstructed to 1 mm",
        "",
        "Mean over "
        + ("all k phases" if args.phases == 0 else f"{args.phases} phase(s)")
        + " of the kept slices. Our methods with tapered end caps (the pipeline default) and "
        "with flat caps (as ITK, which does not extrapolate beyond the end slices). Volume "
        "error = (reconstructed - reference) / reference voxels.",
        "",
        "### Phantoms",
        "",
        kth_section(kth_ph, ph_cases),
    ]
    if real_cases:
        best, loco = choose_default(kth_real) if set(EXPERT) <= set(real_cases) else ("", [])
        lines += ["### Real labels", "", kth_section(kth_real, real_cases)]
        lines += [
            "### Real labels, thick slices as the evaluation flow emulates them",
            "",
            "`tumor3d.evaluation.emulate` forms a 2 mm slice from two whole thin slices "
            "(mean >= 0.5, i.e. their union, centred between them); `slab='flush'` here. "
            "k = 5, taper caps for ours, every phase; the reconstruction is made on a 0.5 mm "
            "grid and sampled on the thin slices. Every method, ITK included, comes out "
            "larger than the reference: the union of two thin labels enlarges each kept "
            "slice, so this bias belongs to the emulation, not to the interpolation.",
            "",
            kth_section(flush_real, real_cases),
        ]
        if best:
            lines += [
                "### Choice of the default",
                "",
                "Rule: highest mean 3-D Dice over "
                "the three expert cases at k = 5 (taper caps, every phase); methods whose paired "
                "(case, phase) mean Dice difference to the best is within two standard errors "
                "count as tied, and among them the smallest mean |volume error| wins (volume is "
                "what the paper estimates; the tie rule was added after a first run showed three "
                f"methods within 0.0002 in Dice). Result: **{best}**"
                + (
                    " = the pipeline default."
                    if best == DEFAULT_LABEL
                    else f" (the code default is {DEFAULT_LABEL}: UPDATE IT)."
                )
                + " Leave-one-case-out (the rule on two cases, scored on the third):",
                "",
                *[f"- {s}" for s in loco],
                "",
            ]
    lines += [targets_section(t4_ph, t4_real, kth_real, flush_real)]
    if missing:
        lines += [f"Skipped (not in {data_dir()}): {', '.join(missing)}.", ""]
    if not args.no_bench:
        sys.path.insert(0, str(Path(__file__).resolve().parent))
        from bench_interpolate import benchmark_markdown

        lines += [benchmark_markdown()]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    pd.DataFrame(kth_ph + kth_real + flush_real).to_csv(
        args.out.with_suffix(".kth.csv"), index=False
    )
    pd.DataFrame(t4_ph + t4_real).to_csv(args.out.with_suffix(".table4.csv"), index=False)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    code = main()
    sys.stdout.flush()
    sys.stderr.flush()
    # ITK's TBB teardown has crashed the interpreter at exit after long runs
    # (malloc corruption, after all output was written): skip the teardown.
    os._exit(code)
