"""Does a second or third co-registered sequence help the learned model? CV by patient.

The BraTS patients of ``$TUMOR3D_DATA_DIR`` have several co-registered
sequences (BraTS 2018 x7 and the algoseg case: FLAIR, T2, T1c; BraTS 2013
x3: FLAIR and T1c). Each case is cut to the paper's acquisition as
``benchmarks/learned_cv.py`` cuts it (31 slabs of 2 mm every 5 mm, robust
prior per sequence, same scoring: 3-D Dice against the 1 mm label after
interpolation, Eq. 7 volume error), and every variant is scored on the
**same patients** out of fold, by patient (``--folds K``: the sorted patients
dealt round-robin into K folds; 0, the default: leave one patient out): for
each held-out fold, every model is trained on the same other patients (rows
of the same pixels: the sampling of a patient is drawn once, on the FLAIR's
tissue, and shared by every variant). Variants, for the whole tumour
(label > 0, the FLAIR reference):

- ``flair``: FLAIR features alone (the shipped features, a FLAIR-only model),
- ``flair+t2``, ``flair+t2+t1c``, ``flair+t1c``: the sequences' features side
  by side (:func:`tumor3d.learned.multiseq.stack_features`),
- ``late(...)``: the mean of single-sequence models' probabilities (each
  sequence's own model trained on the same patients to the whole tumour),
- ``shipped``: the shipped configuration's out-of-fold rows (5 folds, trained
  with the LGG heads, phantoms and T2 too), read from ``--shipped-json``
  (``learned_cv.py --method learned ... --json``), when given; with
  ``--shipped-prob`` (its ``--save-prob`` folder) also the shipped model's
  FLAIR and T2 probabilities averaged (late fusion without training).

Experiments: ``wt3`` (whole tumour, the 8 patients with FLAIR, T2 and T1c),
``wt2`` (whole tumour, the 11 patients with FLAIR and T1c) and ``core`` (the
T1c family's target, tumour core, 11 patients: T1c alone against T1c + FLAIR).

Usage::

    TUMOR3D_DATA_DIR=/work/shared/data python benchmarks/multiseq_cv.py --folds 4 \\
        --cache /tmp/cv-cache --json multiseq.json
    python benchmarks/multiseq_cv.py --rows multiseq.json --shipped-json learned.json \\
        --shipped-prob learned-prob
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from learned_cv import Prepared, cached_prepare, case_specs, score  # noqa: E402

from tumor3d.config import parse_config  # noqa: E402
from tumor3d.learned.features import PatientFeatures, compute_features  # noqa: E402
from tumor3d.learned.forest import predict_proba  # noqa: E402
from tumor3d.learned.multiseq import (  # noqa: E402
    order_sequences,
    sequence_columns,
    stack_features,
)
from tumor3d.learned.segment import keep_main_lesion  # noqa: E402
from tumor3d.learned.training import TrainingRows, sample_indices, train_forest  # noqa: E402
from tumor3d.storage.manifest import data_dir  # noqa: E402

#: experiment -> (target sequence, sequences every patient must have, variants).
#: A variant is a tuple of sequences (features side by side) or ("late", seqs...).
EXPERIMENTS: dict[str, tuple[str, tuple[str, ...], tuple[tuple[str, ...], ...]]] = {
    "wt3": (
        "flair",
        ("flair", "t2", "t1c"),
        (
            ("flair",),
            ("flair", "t2"),
            ("flair", "t2", "t1c"),
            ("late", "flair", "t2"),
            ("late", "flair", "t2", "t1c"),
        ),
    ),
    "wt2": (
        "flair",
        ("flair", "t1c"),
        (("flair",), ("flair", "t1c"), ("late", "flair", "t1c")),
    ),
    "core": ("t1c", ("flair", "t1c"), (("t1c",), ("flair", "t1c"))),
}
#: Probability cut per target (the shipped models': FLAIR + T2 0.5, T1c 0.65).
THRESHOLD = {"flair": 0.5, "t1c": 0.65}
SHIPPED_GROUP = {"flair": "brats_flair", "t1c": "brats_t1c"}


def variant_name(v: tuple[str, ...]) -> str:
    return f"late({'+'.join(v[1:])})" if v[0] == "late" else "+".join(v)


def _assemble(
    full: dict[str, PatientFeatures], seqs: tuple[str, ...], sel: np.ndarray | None = None
) -> np.ndarray:
    """The columns of ``stack_features(seqs)`` (rows ``sel``) from per-sequence features."""
    seqs = order_sequences(seqs)
    cols = sequence_columns()
    take = slice(None) if sel is None else sel
    parts = [full[seqs[0]].values[take]] + [full[s].values[take][:, cols] for s in seqs[1:]]
    return parts[0] if len(parts) == 1 else np.hstack(parts)


def _mask(prob: np.ndarray, p: Prepared, threshold: float, cfg) -> np.ndarray:
    """The harness's post-processing: main lesion (keep-fraction 1.0), small slices cleared."""
    vox = float(np.prod(p.spacing_mm))
    mask = keep_main_lesion(
        prob, threshold, keep_fraction=1.0, min_voxels=max(1, int(round(20.0 / vox)))
    )
    mask[mask.sum(axis=(1, 2)) < cfg.segment.min_tumor_pixels] = False
    return mask


def _oof_prob(
    feats, sel_of, train: list[str], held_out: list[str], seqs: tuple[str, ...]
) -> dict[str, np.ndarray]:
    """Probability maps of ``held_out`` from a model on ``seqs`` trained on ``train``."""
    t1 = time.perf_counter()
    parts = []
    for pat in train:
        sel, y, w = sel_of[pat]
        parts.append(TrainingRows(_assemble(feats[pat], seqs, sel), y, w))
    model = train_forest(TrainingRows.concatenate(parts))
    out = {}
    for held in held_out:
        f = feats[held][order_sequences(seqs)[0]]
        prob = np.zeros(f.shape, np.float32)
        prob.ravel()[f.index] = predict_proba(model, _assemble(feats[held], seqs))
        out[held] = prob
    print(f"    {held_out} {'+'.join(seqs)}: {time.perf_counter() - t1:.0f} s", flush=True)
    return out


def run_experiment(
    name: str, preps: dict[str, dict[str, Prepared]], cfg, folds: int = 0
) -> list[dict]:
    """Every variant of experiment ``name``, out of fold.

    ``folds`` = 0: leave one patient out; else ``folds`` folds, the sorted
    patients dealt round-robin (fold = position mod ``folds``).
    """
    target, need, variants = EXPERIMENTS[name]
    pats = sorted(p for p, d in preps.items() if all(s in d for s in need))
    k = len(pats) if folds <= 0 else min(int(folds), len(pats))
    fold_of = {p: i % k for i, p in enumerate(pats)}
    print(f"{name}: {len(pats)} patients in {k} folds {fold_of}", flush=True)
    used = sorted({s for v in variants for s in (v[1:] if v[0] == "late" else v)})
    feats: dict[str, dict[str, PatientFeatures]] = {}
    sel_of: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    t0 = time.perf_counter()
    for i, pat in enumerate(pats):
        d = preps[pat]
        primary = order_sequences(used)[0]  # whose tissue gives the rows
        ref = d[primary]
        full = {}
        for s in order_sequences(used):
            q = d[s]
            full[s] = compute_features(
                q.image,
                spacing_mm=ref.spacing_mm,
                modality=s,
                lr_axis=ref.lr_axis,
                prior=q.prior,
                candidates=None if s == primary else full[primary].candidates,
            )
        if i == 0:  # the assembly here is stack_features' (checked once per experiment)
            check = stack_features(
                {s: d[s].image for s in used},
                spacing_mm=ref.spacing_mm,
                lr_axis=ref.lr_axis,
                priors={s: d[s].prior for s in used},
            )
            assert np.array_equal(check.values, _assemble(full, tuple(used)))
        feats[pat] = full
        # one draw of rows per patient (on the primary's tissue), shared by every variant
        sel_of[pat] = sample_indices(full[primary], d[target].ref, rng=np.random.default_rng(i))
    print(f"  features in {time.perf_counter() - t0:.0f} s", flush=True)

    out = []
    thr = THRESHOLD[target]
    for j in range(k):
        held_out = [p for p in pats if fold_of[p] == j]
        train = [p for p in pats if fold_of[p] != j]
        single: dict[str, dict[str, np.ndarray]] = {}
        for v in variants:
            if v[0] == "late":
                for s in v[1:]:
                    if s not in single:
                        single[s] = _oof_prob(feats, sel_of, train, held_out, (s,))
                probs = {h: np.mean([single[s][h] for s in v[1:]], axis=0) for h in held_out}
            else:
                probs = _oof_prob(feats, sel_of, train, held_out, v)
                if len(v) == 1:
                    single[v[0]] = probs
            for held in held_out:
                p_ref = preps[held][target]
                row = score(p_ref, _mask(probs[held], p_ref, thr, cfg), cfg)
                row.update(experiment=name, variant=variant_name(v), patient=held, fold=j)
                out.append(row)
                print(
                    f"  {held} {variant_name(v)}: 3d {row['dice3d']:.3f} "
                    f"vol {row['vol_err']:+.1f}%",
                    flush=True,
                )
    return out


def _figures(rs: list[dict]) -> str:
    d = np.array([r["dice3d"] for r in rs])
    v = np.array([r["vol_err"] for r in rs])
    s = np.array([r["slice_dice"] for r in rs])
    e = np.abs(v)
    return (
        f"{len(rs)} | {np.mean(s):.3f} | {np.mean(d):.3f} ± {np.std(d):.3f} ({np.median(d):.3f})"
        f" | {np.mean(e):.1f} % ({np.median(v):+.1f} %) | {int(np.sum(e <= 10))} / "
        f"{int(np.sum(e > 25))}"
    )


def _paired(base: list[dict], other: list[dict]) -> str:
    """Paired change of 3-D Dice and |volume error| (other - base), per patient."""
    from scipy import stats

    b = {r["patient"]: r for r in base}
    pats = [r["patient"] for r in other if r["patient"] in b]
    o = {r["patient"]: r for r in other}
    dd = np.array([o[p]["dice3d"] - b[p]["dice3d"] for p in pats])
    de = np.array([abs(o[p]["vol_err"]) - abs(b[p]["vol_err"]) for p in pats])
    n = dd.size
    sd = float(np.std(dd, ddof=1)) if n > 1 else float("nan")
    half = float(stats.t.ppf(0.975, n - 1) * sd / np.sqrt(n)) if n > 1 else float("nan")
    # exact sign-flip test of the mean Dice change (2^n sign patterns)
    signs = np.array(np.meshgrid(*[[-1.0, 1.0]] * n)).reshape(n, -1).T
    ad = np.round(dd, 6)  # float16 maps: differences below 1e-6 are ties
    perm = np.abs(signs @ np.abs(ad)) >= abs(ad.sum()) - 1e-9
    return (
        f"{np.mean(dd):+.3f} ± {sd:.3f} | [{np.mean(dd) - half:+.3f}, {np.mean(dd) + half:+.3f}]"
        f" | {float(perm.mean()):.2f} | {int(np.sum(dd > 0.005))} / {int(np.sum(dd < -0.005))}"
        f" | {np.mean(de):+.1f} pt"
    )


def shipped_late_rows(preps: dict[str, dict[str, Prepared]], folder: Path, cfg) -> list[dict]:
    """The shipped configuration's out-of-fold probabilities, alone and averaged over sequences.

    ``folder`` holds ``learned_cv.py --save-prob`` maps (``<patient>__<seq>.npz``,
    key ``prob``; an ``--auto-context`` run's ``prob1`` is its first stage, the
    shipped model). A patient's sequences share a fold there, so the mean of its
    FLAIR and T2 maps is out of fold too: late fusion with the shipped model.
    """

    def load(pat: str, seq: str) -> np.ndarray:
        with np.load(folder / f"{pat}__{seq}.npz", allow_pickle=False) as z:
            return z["prob1" if "prob1" in z.files else "prob"].astype(np.float32)

    out = []
    for name, (target, need, _) in EXPERIMENTS.items():
        if target != "flair":
            continue
        fused = tuple(s for s in need if s in ("flair", "t2"))  # the hyper model's sequences
        for pat in sorted(p for p, d in preps.items() if all(s in d for s in need)):
            p_ref = preps[pat][target]
            maps = {s: load(pat, s) for s in fused}
            variants = {"shipped model, flair": maps["flair"]}
            if len(fused) > 1:
                variants[f"shipped model, late({'+'.join(fused)})"] = np.mean(
                    list(maps.values()), axis=0
                )
            for v, prob in variants.items():
                row = score(p_ref, _mask(prob, p_ref, THRESHOLD[target], cfg), cfg)
                row.update(experiment=name, variant=v, patient=pat)
                out.append(row)
    return out


def _fold_words(rows: list[dict], n_patients: int) -> str:
    k = len({r.get("fold") for r in rows if not r["variant"].startswith("shipped")})
    return "leave one patient out" if k == n_patients else f"{k} folds by patient"


def report(rows: list[dict], shipped: list[dict] | None) -> str:
    lines = []
    for name, (target, need, variants) in EXPERIMENTS.items():
        rs = [r for r in rows if r["experiment"] == name]
        if not rs:
            continue
        pats = sorted({r["patient"] for r in rs})
        names = [variant_name(v) for v in variants]
        names += [n for n in dict.fromkeys(r["variant"] for r in rs) if n not in names]
        by = {n: [r for r in rs if r["variant"] == n] for n in names}
        by = {n: v for n, v in by.items() if v}
        if shipped is not None:
            g = SHIPPED_GROUP[target]
            sh = [
                {**r, "patient": r["case"].split("/")[0]}
                for r in shipped
                if r["group"] == g and r["case"].split("/")[0] in pats
            ]
            if len(sh) == len(pats):
                by = {"shipped (5-fold, all data)": sh, **by}
        base_name = variant_name(variants[0])
        if base_name not in by:
            base_name = next(n for n in by if not n.startswith("shipped (5-fold"))
        lines += [
            "",
            f"Experiment `{name}`: target {'whole tumour' if target == 'flair' else 'tumour core'}"
            f", {len(pats)} patients with {', '.join(need)}, out of fold "
            f"({_fold_words(rs, len(pats))})",
            "",
            "| variant | n | per-slice Dice | 3-D Dice mean ± sd (median) | volume error mean abs "
            "(median) | within 10 % / beyond 25 % |",
            "|---|---|---|---|---|---|",
        ]
        lines += [f"| {k} | {_figures(v)} |" for k, v in by.items()]
        lines += [
            "",
            f"Paired change against `{base_name}` (same patients, same training patients):",
            "",
            "| variant | 3-D Dice change mean ± sd | 95 % t-interval | sign-flip p "
            "| better / worse (> 0.005) | abs volume error change |",
            "|---|---|---|---|---|---|",
        ]
        lines += [f"| {k} | {_paired(by[base_name], v)} |" for k, v in by.items() if k != base_name]
        sh_name = next((n for n in by if n.startswith("shipped (5-fold")), None)
        if sh_name:
            lines += [
                "",
                f"Paired change against `{sh_name}` (same patients; its models saw more data):",
                "",
                "| variant | 3-D Dice change mean ± sd | 95 % t-interval | sign-flip p "
                "| better / worse (> 0.005) | abs volume error change |",
                "|---|---|---|---|---|---|",
            ]
            lines += [
                f"| {k} | {_paired(by[sh_name], v)} |"
                for k, v in by.items()
                if k != sh_name and k != "shipped model, flair"
            ]
        lines += ["", "Per patient, 3-D Dice:", ""]
        names = list(by)
        lines += ["| patient | " + " | ".join(names) + " |", "|---" * (len(names) + 1) + "|"]
        for p in pats:
            cells = []
            for k in names:
                r = next((r for r in by[k] if r["patient"] == p), None)
                cells.append("" if r is None else f"{r['dice3d']:.3f}")
            lines.append(f"| {p} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default=str(ROOT / "configs" / "default.yaml"))
    ap.add_argument("--experiments", nargs="*", default=list(EXPERIMENTS))
    ap.add_argument("--cache", default=None, help="learned_cv.py's prepared-case cache")
    ap.add_argument(
        "--folds", type=int, default=0, help="folds by patient (0: leave one patient out)"
    )
    ap.add_argument("--shipped-json", default=None, help="learned_cv.py --json of the shipped run")
    ap.add_argument("--json", default=None, help="write the per-case rows here")
    ap.add_argument("--rows", default=None, help="report the rows of an earlier --json only")
    ap.add_argument(
        "--shipped-prob",
        default=None,
        help="learned_cv.py --save-prob folder of the shipped run: adds the shipped model "
        "alone and averaged over FLAIR and T2 (late fusion, no training)",
    )
    args = ap.parse_args(argv)
    shipped = json.loads(Path(args.shipped_json).read_text()) if args.shipped_json else None
    earlier = json.loads(Path(args.rows).read_text()) if args.rows else None
    if earlier is not None and not args.shipped_prob:
        print(report(earlier, shipped))
        return 0
    data = data_dir()
    if not data.is_dir():
        print(f"skipped: no real data at {data} (set TUMOR3D_DATA_DIR)")
        return 0
    cfg = parse_config(Path(args.config).read_text(), source=args.config)
    specs = [s for s in case_specs(data) if s.group in ("brats_flair", "brats_t2", "brats_t1c")]
    t0 = time.perf_counter()
    preps: dict[str, dict[str, Prepared]] = {}
    for s in specs:
        preps.setdefault(s.patient, {})[s.modality] = cached_prepare(s, cfg, True, args.cache)
    print(f"prepared {len(specs)} cases in {time.perf_counter() - t0:.0f} s", flush=True)
    rows: list[dict] = []
    if earlier is not None:
        rows = [r for r in earlier if not r["variant"].startswith("shipped model")]
    else:
        for name in args.experiments:
            rows += run_experiment(name, preps, cfg, args.folds)
            if args.json:
                Path(args.json).write_text(json.dumps(rows, indent=1))
    if args.shipped_prob:
        rows += shipped_late_rows(preps, Path(args.shipped_prob), cfg)
        if args.json:
            Path(args.json).write_text(json.dumps(rows, indent=1))
    print(report(rows, shipped))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
