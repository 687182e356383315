"""Cross-validation by patient of a small 2-D U-Net, paired with the shipped learned model.

An experiment (issue 28): does a per-slice CNN, which sees the context of a
raw head, beat the shipped voxel forest (``segment.method: learned``)? Same
cases, same folds and same scoring as ``benchmarks/learned_cv.py`` (its case
listing, fold assignment, preparation cache, post-processing and
:func:`learned_cv.score`): BraTS FLAIR cut to 31 slabs of 2 mm every 5 mm
(3-D Dice against the 1 mm label after interpolation), the clinical LGG FLAIR
heads at their native slices.

The network (``tumor3d.learned.cnn`` documents it): a U-Net of 4 levels,
``--base`` channels at the top, on ``--size`` x ``--size`` slices (the whole
slice resampled), 2.5-D (the slice and ``--context`` neighbours each side as
channels), intensity ``(I - median) / robust SD`` over the head's tissue per
patient (``tumor3d.learned.features.normalise_intensity``, as the forest's
features). One network per fold, trained on the FLAIR of the other folds'
patients (LGG heads and BraTS slabs together), binary cross-entropy + soft
Dice, Adam with a one-cycle learning rate (15 % warm-up, cosine decay), each
epoch every tumour slice and ``--neg-ratio`` times as many slices without
tumour drawn at random, left-right flips, shifts and intensity jitter.
Post-processing as the shipped model: threshold 0.5, the main 3-D region
(``keep_fraction`` 1.0), small slice masks cleared.

PyTorch stays out of the project's environment: this script prepares the
slices with the project's code, runs the training in ``--torch-python`` (a
separate venv with torch + numpy; the same file in ``--worker`` mode, which
imports only ``tumor3d.learned.cnn_train``: the network, its training loop and
the weight export, numpy + torch), then scores with the project's code. The
trained weights (batch norm folded) are written for the numpy forward pass
``tumor3d.learned.cnn``, which is timed here on a 31 x 240 x 240 patient.

``--final OUT.npz`` trains the shipped network instead: one net on every case
of every fold (the same cases and settings, ``--seed``), its metadata
(``meta_json``: cases per group, settings, torch version, date, wall time and
load) in the file, and checks the numpy forward pass against torch on one case.

Usage (the figures of ``reports/learned_cv.md``; ``learned.json`` and the
``--save-prob`` folder come from the shipped model's cross-validation,
``learned_cv.py --method learned ... --json learned.json --save-prob prob``)::

    python3 -m venv /work/torchvenv && /work/torchvenv/bin/pip install torch==2.13.0 numpy
    TUMOR3D_DATA_DIR=../shared/data nice -n 10 python benchmarks/cnn_cv.py \
        --cache /tmp/cv-cache --work /tmp/cnn --paired learned.json \
        --forest-prob prob --json cnn.json
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
#: ``--groups`` (default: the FLAIR ones, the shipped net's); ``brats_t2``: the BraTS T2 slabs
#: in the training and the scoring too (a FLAIR + T2 net).
GROUP_CODE = {"lgg": 0, "brats_flair": 1, "brats_t2": 2}
#: Fold k's net starts from seed ``k + FOLD_SEED_STEP * --seed`` (``--seed 0``: seed k).
FOLD_SEED_STEP = 1000


# ---------------------------------------------------------------- preparation (project venv)


def build_dataset(preps, folds, args) -> dict[str, np.ndarray]:
    from real_segmentation import emulate_thick

    from tumor3d.learned.cnn_data import case_input, case_target, frame_of

    xs, ys, fold, case, train_only, group = [], [], [], [], [], []
    for ci, p in enumerate(preps):
        k = folds[p.spec.patient]
        views = [(p.image, p.ref, False)]
        if not p.spec.native and p.raw is not None:
            for off in args.train_offsets:
                if off != 2:  # learned_cv.OFFSET is the scored cut
                    views.append(
                        (
                            emulate_thick(p.raw, off).astype(np.float32),
                            emulate_thick(p.label, off) >= 0.5,
                            True,
                        )
                    )
        for img, ref, extra in views:
            frame = frame_of(img, args.framing, p.pixel_mm)
            x = case_input(img, args.size, args.context, frame)
            xs.append(x)
            ys.append(case_target(ref, args.size, frame))
            n = x.shape[0]
            fold.append(np.full(n, k, np.int8))
            case.append(np.full(n, ci, np.int32))
            train_only.append(np.full(n, extra))
            group.append(np.full(n, GROUP_CODE[p.spec.group], np.int8))
    return {
        "x": np.concatenate(xs),
        "y": np.concatenate(ys),
        "fold": np.concatenate(fold),
        "case": np.concatenate(case),
        "train_only": np.concatenate(train_only),
        "group": np.concatenate(group),
        "names": np.array([p.spec.name for p in preps]),
    }


# ---------------------------------------------------------------- training (torch venv)


#: The options that are :class:`tumor3d.learned.cnn_train.UNetSettings` fields (the
#: training workers get them all).
TRAIN_OPTIONS = ("size", "context", "base", "levels", "epochs", "batch", "lr", "neg_ratio",
                 "shift", "scale", "rotate_deg", "framing", "slice_dice")  # fmt: skip


def _settings(args):
    from tumor3d.learned.cnn_train import UNetSettings

    return UNetSettings(**{k: getattr(args, k) for k in TRAIN_OPTIONS})


def worker_final(args) -> int:
    """``--final``: one net on every row of ``data.npz`` (all folds), weights + metadata."""
    import datetime

    from tumor3d.learned.cnn_train import torch_probability, train_unet

    work = Path(args.work)
    with np.load(work / "data.npz", allow_pickle=False) as z:
        x_all, y_all, case_of = z["x"], z["y"], z["case"]
    meta = json.loads((work / "final_meta.json").read_text())
    meta["trained_utc"] = datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds")
    load0 = os.getloadavg()[0]
    data, fit = train_unet(
        x_all, y_all, _settings(args), seed=args.seed, threads=args.threads, meta=meta,
        log=lambda line: print(f"final {line}", flush=True),
    )  # fmt: skip
    first = np.flatnonzero(case_of == case_of[0])  # a check of the export: torch's own output
    np.savez(work / "final_check.npz", index=first, prob=torch_probability(fit.model, x_all[first]))
    load1 = os.getloadavg()[0]
    # the load during the training, added after the fact (the weights are final)
    from tumor3d.learned.cnn_train import unet_meta, unet_to_bytes

    meta = {**unet_meta(data), "load_1min_start_end": [round(load0, 2), round(load1, 2)],
            "torch_threads": args.threads}  # fmt: skip
    Path(args.final).write_bytes(unet_to_bytes(fit.model, meta))
    print(f"final: trained in {fit.seconds:.0f} s, written {args.final}", flush=True)
    return 0


def worker(args) -> int:
    sys.path.insert(0, str(ROOT))  # tumor3d.learned.cnn_train: numpy + torch only
    if args.final:
        return worker_final(args)
    from tumor3d.learned.cnn_train import fit_unet, torch_probability, unet_to_bytes

    work = Path(args.work)
    with np.load(work / "data.npz", allow_pickle=False) as z:
        d = {k: z[k] for k in z.files}
    x_all, y_all = d["x"], d["y"]
    settings = _settings(args)
    timing = {}
    for k in args.run_folds:
        tr = np.flatnonzero(d["fold"] != k)
        held = np.flatnonzero((d["fold"] == k) & ~d["train_only"])
        fit = fit_unet(
            x_all, y_all, settings, seed=k + FOLD_SEED_STEP * args.seed, rows=tr,
            threads=args.threads, log=lambda line, k=k: print(f"fold {k} {line}", flush=True),
        )  # fmt: skip
        t1 = time.perf_counter()
        probs = torch_probability(fit.model, x_all[held]).astype(np.float16)
        infer_s = time.perf_counter() - t1
        np.savez(work / f"prob_fold{k}.npz", index=held, prob=probs)
        # the settings in the file: its grid and framing (UNetWeights.size / context / framing)
        meta = {"settings": dataclasses.asdict(settings), "fold": k}
        (work / f"unet_fold{k}.npz").write_bytes(unet_to_bytes(fit.model, meta))
        timing[k] = {
            "train_s": fit.seconds,
            "infer_s": infer_s,
            "held_slices": int(len(held)),
            "train_slices_per_epoch": fit.slices_per_epoch,
        }
        (work / f"timing_fold{k}.json").write_text(json.dumps(timing[k]))
        print(
            f"fold {k}: trained in {fit.seconds:.0f} s, {len(held)} slices in {infer_s:.1f} s",
            flush=True,
        )
    return 0


# ---------------------------------------------------------------- scoring (project venv)


def _metric_line(g: str, pairs: list, key: str, label: str, digits: int = 3) -> str:
    """One row of :func:`paired_table`: ``key`` of the (other, new) row ``pairs`` of ``g``."""
    from scipy.stats import wilcoxon

    def val(r):
        return abs(r["vol_err"]) if key == "abs_vol_err" else r[key]

    a = np.array([val(o) for o, _ in pairs], float)
    b = np.array([val(c) for _, c in pairs], float)
    ok = np.isfinite(a) & np.isfinite(b)
    a, b = a[ok], b[ok]
    diff = b - a
    tol = 1.0 if key == "abs_vol_err" else 0.01  # a change smaller counts as none
    better = int(np.sum(diff < -tol)) if key == "abs_vol_err" else int(np.sum(diff > tol))
    worse = int(np.sum(diff > tol)) if key == "abs_vol_err" else int(np.sum(diff < -tol))
    try:
        pval = f"{wilcoxon(a, b).pvalue:.3g}" if np.any(diff != 0) else "1"
    except ValueError:
        pval = "n/a"
    d = digits
    return (
        f"| {g} | {len(a)} | {label} | {a.mean():.{d}f} ± {a.std():.3f} ({np.median(a):.{d}f})"
        f" | {b.mean():.{d}f} ± {b.std():.3f} ({np.median(b):.{d}f})"
        f" | {diff.mean():+.{d}f} ± {diff.std():.3f} | {better} / {worse} | {pval} |"
    )


def paired_table(cnn_rows: list[dict], other_rows: list[dict], name: str, new: str) -> str:
    """Per group, each target figure paired (``other_rows`` -> ``cnn_rows``); with more
    than one group, a last row of the pooled 3-D Dice."""
    other = {r["case"]: r for r in other_rows}
    lines = [
        f"| group | n | metric | {name} mean ± sd (median) | {new} mean ± sd (median) | "
        "paired difference mean ± sd | better / worse by > 0.01 (1 %) | Wilcoxon p |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for g in GROUP_CODE:
        pairs = [(other[r["case"]], r) for r in cnn_rows if r["group"] == g and r["case"] in other]
        if not pairs:
            continue
        for key, label in (
            ("dice3d", "3-D Dice"),
            ("slice_dice", "per-slice Dice"),
            ("recall", "slice recall"),
            ("spec", "slice specificity"),
            ("abs_vol_err", "abs. volume error %"),
        ):
            lines.append(_metric_line(g, pairs, key, label))
        ea = np.array([abs(o["vol_err"]) for o, _ in pairs])
        eb = np.array([abs(c["vol_err"]) for _, c in pairs])
        lines.append(
            f"| {g} | {len(pairs)} | volumes within 10 % / beyond 25 % | "
            f"{int(np.sum(ea <= 10))} / {int(np.sum(ea > 25))} | "
            f"{int(np.sum(eb <= 10))} / {int(np.sum(eb > 25))} | | | |"
        )
    pooled = [(other[r["case"]], r) for r in cnn_rows if r["case"] in other]
    if len({r["group"] for _, r in pooled}) > 1:
        lines.append(_metric_line("pooled", pooled, "dice3d", "3-D Dice", digits=4))
    return "\n".join(lines)


def score_folds(preps, folds, run_folds, case_of, train_only, args, cfg):
    """Out-of-fold rows of the U-Net, and (``args.forest_prob``) of the forest and the mean.

    The U-Net's probabilities are ``args.work``'s ``prob_fold{k}.npz`` (torch's), or with
    ``args.mirror`` the pipeline's numpy pass of ``unet_fold{k}.npz`` with its mirrored
    pass averaged in (``unet_probability(..., mirror=True)``); every map gets
    the shipped model's post-processing (``args.threshold``, the main 3-D region at
    ``args.keep_fraction``, small slice masks cleared) and :func:`learned_cv.score`.
    """
    import learned_cv as L

    from tumor3d.learned.cnn_data import frame_of, upsample

    work = Path(args.work)
    rows: list[dict] = []
    forest_rows: list[dict] = []  # the shipped model's saved probabilities, scored here
    mean_rows: list[dict] = []  # the mean of the two probabilities (fixed equal weights)

    def scored(p, pr, k, out, label):
        mask = L.keep_main_lesion(
            pr, args.threshold, keep_fraction=args.keep_fraction, min_voxels=L._min_voxels(p)
        )
        mask[mask.sum(axis=(1, 2)) < cfg.segment.min_tumor_pixels] = False
        row = L.score(p, mask, cfg)
        row["fold"] = k
        out.append(row)
        print(
            f"  {label:6s} {row['case']}: slice {row['slice_dice']:.3f} 3d {row['dice3d']:.3f} "
            f"vol {row['vol_err']:+.1f}% rec {row['recall']:.2f} spec {row['spec']:.2f}",
            flush=True,
        )

    x_all = None
    if args.mirror or args.ensemble_work:  # the pipeline's inference: numpy (mirrored pass
        from tumor3d.learned.cnn import unet_probability  # with --mirror)

        with np.load(work / "data.npz", allow_pickle=False) as z:
            x_all = z["x"]
    from tumor3d.learned.cnn import unet_from_bytes

    for k in run_folds:
        # the held-out probabilities are put back through --framing's window: the fold
        # nets must have seen that window (their files say which)
        dirs = [work] + ([Path(args.ensemble_work)] if args.ensemble_work else [])
        nets = [unet_from_bytes((d / f"unet_fold{k}.npz").read_bytes()) for d in dirs]
        for d, net in zip(dirs, nets, strict=True):
            if net.framing != args.framing:
                raise SystemExit(
                    f"{d / f'unet_fold{k}.npz'}: a net trained with framing {net.framing!r}; "
                    f"run with --framing {net.framing}"
                )
        with np.load(work / f"prob_fold{k}.npz", allow_pickle=False) as z:
            index, prob = z["index"], z["prob"]
        if x_all is not None:
            # the pipeline's inference; with --ensemble-work the mean of the two trainings
            probs = [unet_probability(n, x_all[index], mirror=args.mirror) for n in nets]
            prob = probs[0] if len(probs) == 1 else 0.5 * (probs[0] + probs[1])
        for ci, p in enumerate(preps):
            if folds[p.spec.patient] != k:
                continue
            sel = index[case_of[index] == ci]
            assert not train_only[sel].any() and len(sel) == p.image.shape[0]
            frame = frame_of(p.image, args.framing, p.pixel_mm)
            pr = upsample(prob[np.searchsorted(index, sel)], p.image.shape, frame)
            scored(p, pr, k, rows, "U-Net")
            if args.forest_prob:
                f = L.case_file(args.forest_prob, p.spec.name)
                with np.load(f, allow_pickle=False) as z:
                    # a case the shipped run segmented with the forest alone (T2) saved its
                    # map as ``prob`` only: that map is the forest's
                    key = args.forest_key if args.forest_key in z.files else "prob"
                    if key != args.forest_key and "cnn" in z.files:
                        raise SystemExit(f"{f} has no {args.forest_key!r} map")
                    pf = z[key].astype(np.float32)
                scored(p, pf, k, forest_rows, "forest")
                scored(p, 0.5 * (pr + pf), k, mean_rows, "mean")
    return rows, forest_rows, mean_rows


def time_numpy_forward(weights: Path, args, repeats: int = 3) -> dict:
    """Seconds of the numpy forward pass (``tumor3d.learned.cnn``) on a 31 x 240 x 240 patient."""
    from tumor3d.learned.cnn import unet_from_bytes, unet_probability
    from tumor3d.learned.cnn_data import case_input, upsample

    net = unet_from_bytes(Path(weights).read_bytes(), source=str(weights))
    rng = np.random.default_rng(0)
    vol = rng.normal(100, 20, (31, 240, 240)).astype(np.float32)
    best = {}
    for _ in range(repeats):
        t0 = time.perf_counter()
        x = case_input(vol, args.size, args.context)
        t1 = time.perf_counter()
        c1 = time.process_time()
        prob = unet_probability(net, x)
        c2 = time.process_time()
        t2 = time.perf_counter()
        upsample(prob, vol.shape)
        t3 = time.perf_counter()
        for k, v in (
            ("input", t1 - t0),
            ("network", t2 - t1),
            ("network_cpu", c2 - c1),
            ("upsample", t3 - t2),
            ("total", t3 - t0),
        ):
            best[k] = min(best.get(k, np.inf), v)
    best["load_1min"] = os.getloadavg()[0]
    return best


def _sequences(groups) -> list[str]:
    """The sequences the ``--groups`` hold, for the final net's metadata.

    >>> _sequences(["lgg", "brats_flair", "brats_t2"])
    ['FLAIR', 'T2']
    """
    return ["FLAIR"] + (["T2"] if "brats_t2" in groups else [])


def train_final(preps, folds, args, work: Path) -> int:
    """``--final``: the dataset of every case (all folds), one torch worker, a check."""
    t0 = time.perf_counter()
    d = build_dataset(preps, folds, args)
    np.savez(work / "data.npz", **d)
    print(f"dataset {d['x'].shape} in {time.perf_counter() - t0:.0f} s", flush=True)
    groups = {g: sorted({p.spec.patient for p in preps if p.spec.group == g}) for g in args.groups}
    seqs = _sequences(args.groups)
    meta = {
        "model": f"tumor3d 2-D U-Net, {' + '.join(seqs)} (benchmarks/cnn_cv.py --final)",
        "trained_on": {
            g: {
                "cases": sum(p.spec.group == g for p in preps),
                "patients": len(groups[g]),
                "names": [p.spec.name for p in preps if p.spec.group == g],
            }
            for g in args.groups
        },
        "data": "lgg: clinical FLAIR heads at their native slices; brats_flair"
        + (" and brats_t2: BraTS 2018 FLAIR and T2" if "T2" in seqs else ": BraTS 2018 FLAIR")
        + " cut to 2 mm slabs every 5 mm (offsets "
        + ",".join(map(str, args.train_offsets))
        + ")",
        "settings": {k: getattr(args, k) for k in (*TRAIN_OPTIONS, "train_offsets")},
        "input": "tumor3d.learned.cnn_data.case_input(image, size, context, "
        "frame_of(image, framing, pixel_mm))",
        "loss": "BCE + soft Dice"
        + (
            f" + {args.slice_dice:g} x per-slice soft Dice (the slices with tumour)"
            if args.slice_dice
            else ""
        )
        + "; Adam (weight decay 1e-5), one-cycle lr (15 % warm-up)",
    }
    (work / "final_meta.json").write_text(json.dumps(meta, indent=1))
    out = Path(args.final).resolve()
    out.parent.mkdir(parents=True, exist_ok=True)
    cmd = [
        args.torch_python,
        str(Path(__file__).resolve()),
        "--worker",
        "--work",
        str(work),
        "--final",
        str(out),
        "--seed",
        str(args.seed),
        "--threads",
        str(args.threads),
    ]
    for opt in TRAIN_OPTIONS:
        cmd += [f"--{opt.replace('_', '-')}", str(getattr(args, opt))]
    env = {**os.environ, "OMP_NUM_THREADS": str(args.threads)}
    if subprocess.call(cmd, env=env):
        raise SystemExit("the training worker failed")
    from tumor3d.learned.cnn import unet_from_bytes, unet_probability

    with np.load(work / "final_check.npz", allow_pickle=False) as z:
        first, prob = z["index"], z["prob"]
    p_np = unet_probability(unet_from_bytes(out.read_bytes(), source=str(out)), d["x"][first])
    print(
        f"numpy forward of {out.name} against torch on {len(first)} slices: "
        f"max abs difference {np.abs(p_np - prob).max():.2g}",
        flush=True,
    )
    return 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--run-folds", type=int, nargs="*", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--config", default=str(ROOT / "configs" / "default.yaml"))
    ap.add_argument("--folds", type=int, default=5)
    ap.add_argument(
        "--only-folds",
        type=int,
        nargs="*",
        default=None,
        help="train and score only these folds (a partial run)",
    )
    ap.add_argument("--groups", nargs="*", default=["lgg", "brats_flair"], choices=list(GROUP_CODE))
    ap.add_argument("--cache", default=None, help="learned_cv.py's preparation cache")
    ap.add_argument("--work", default="/tmp/cnn-cv", help="scratch folder (data, weights)")
    ap.add_argument("--torch-python", default="/work/torchvenv/bin/python")
    ap.add_argument("--threads", type=int, default=2, help="torch threads in all")
    ap.add_argument("--workers", type=int, default=2, help="training processes (folds split)")
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--context", type=int, default=1, help="neighbour slices each side")
    ap.add_argument("--base", type=int, default=8)
    ap.add_argument("--levels", type=int, default=4)
    ap.add_argument("--epochs", type=int, default=8)
    ap.add_argument("--batch", type=int, default=16)
    ap.add_argument("--lr", type=float, default=3e-3)
    ap.add_argument("--neg-ratio", type=float, default=0.5)
    ap.add_argument("--shift", type=int, default=8, help="random shift (pixels at --size)")
    ap.add_argument("--scale", type=float, default=0.0, help="random scaling within 1 +- this")
    ap.add_argument("--rotate-deg", type=float, default=0.0, help="random rotation (degrees)")
    ap.add_argument(
        "--slice-dice",
        type=float,
        default=1.0,
        help="weight of a per-slice soft Dice term (the slices with tumour) added to the loss "
        "(the shipped nets' 1 since 2026-12-07, 0 before)",
    )
    ap.add_argument(
        "--framing",
        choices=("slice", "head", "mm"),
        default="mm",
        help="what of each slice the net sees (tumor3d.learned.cnn_data.FRAMINGS; the shipped "
        "nets' mm since 2026-12-07, slice before)",
    )
    ap.add_argument(
        "--train-offsets",
        type=int,
        nargs="*",
        default=[2],
        help="BraTS slab offsets used for training (scored: offset 2)",
    )
    ap.add_argument(
        "--final",
        default=None,
        metavar="OUT.npz",
        help="train ONE net on every case of every fold (the shipped weights) and write it here",
    )
    ap.add_argument(
        "--seed",
        type=int,
        default=0,
        help="--final's seed (torch and numpy); fold k's net: k + 1000 x this",
    )
    ap.add_argument(
        "--ensemble-work",
        default=None,
        help="the U-Net's probability is the mean of this run's fold net and the fold net of "
        "another run's --work (same folds and settings; another --seed), both run by the "
        "pipeline's numpy pass (with --mirror: each with its mirrored pass)",
    )
    ap.add_argument("--threshold", type=float, default=0.5)
    ap.add_argument("--keep-fraction", type=float, default=1.0)
    ap.add_argument(
        "--skip-train", action="store_true", help="score the probabilities already in --work"
    )
    ap.add_argument(
        "--mirror",
        action="store_true",
        help="score the fold nets as the pipeline runs them: numpy, the mean with the "
        "mirrored pass (tumor3d.learned.cnn.unet_probability(..., mirror=True))",
    )
    ap.add_argument(
        "--paired",
        default=None,
        help="learned_cv.py --json rows of the shipped model (same folds) to pair with",
    )
    ap.add_argument("--json", default=None, help="write the per-case rows here")
    ap.add_argument(
        "--forest-prob",
        default=None,
        help="learned_cv.py --save-prob folder of the shipped model's out-of-fold "
        "probabilities (same folds): also score it and the mean of the two",
    )
    ap.add_argument(
        "--forest-key",
        default="prob",
        help="array of those files (prob1: an --auto-context run's stage 1 = the shipped model)",
    )
    args = ap.parse_args(argv)
    if args.worker:
        return worker(args)

    sys.path.insert(0, str(ROOT))
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import learned_cv as L

    cases = L.grouped_cases(args.config, args.folds, args.groups)
    if cases is None:
        return 0
    cfg, specs, folds = cases
    run_folds = list(range(args.folds)) if args.only_folds is None else args.only_folds
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    preps = [L.cached_prepare(s, cfg, False, args.cache) for s in specs]
    print(f"prepared {len(preps)} cases in {time.perf_counter() - t0:.0f} s", flush=True)
    if args.final:
        return train_final(preps, folds, args, work)
    if not args.skip_train:
        t0 = time.perf_counter()
        d = build_dataset(preps, folds, args)
        np.savez(work / "data.npz", **d)
        print(f"dataset {d['x'].shape} in {time.perf_counter() - t0:.0f} s", flush=True)
        # --workers processes, folds dealt round-robin, --threads shared among them
        # (on busy shared cores single-threaded processes waste less in thread sync)
        n_proc = max(1, min(args.workers, len(run_folds)))
        threads = max(1, args.threads // n_proc)
        procs = []
        for w in range(n_proc):
            cmd = [
                args.torch_python,
                str(Path(__file__).resolve()),
                "--worker",
                "--work",
                str(work),
                "--run-folds",
                *map(str, run_folds[w::n_proc]),
                "--threads",
                str(threads),
                "--seed",
                str(args.seed),
            ]
            for opt in TRAIN_OPTIONS:
                cmd += [f"--{opt.replace('_', '-')}", str(getattr(args, opt))]
            env = {**os.environ, "OMP_NUM_THREADS": str(threads)}
            procs.append(subprocess.Popen(cmd, env=env))
        codes = [p.wait() for p in procs]
        if any(codes):
            raise SystemExit("a training worker failed")
    with np.load(work / "data.npz", allow_pickle=False) as z:
        case_of, train_only = z["case"], z["train_only"]
        if "names" in z.files and list(z["names"]) != [p.spec.name for p in preps]:
            raise SystemExit(
                f"{work}/data.npz holds other cases: --skip-train needs the same --groups"
            )
    rows, forest_rows, mean_rows = score_folds(
        preps, folds, run_folds, case_of, train_only, args, cfg
    )
    timing = {k: json.loads((work / f"timing_fold{k}.json").read_text()) for k in run_folds}
    print("U-Net:")
    print(L.summarise(rows))
    for k, t in timing.items():
        print(
            f"fold {k}: training {t['train_s']:.0f} s ({t['train_slices_per_epoch']} slices "
            f"per epoch), {t['held_slices']} held-out slices in {t['infer_s']:.1f} s (torch)"
        )
    k0 = run_folds[0]
    nt = time_numpy_forward(work / f"unet_fold{k0}.npz", args)
    # the numpy forward pass with the exported (batch-norm-folded) weights against the
    # torch model's own held-out probabilities: the first held-out case of that fold
    from tumor3d.learned.cnn import unet_from_bytes, unet_probability

    with np.load(work / f"prob_fold{k0}.npz", allow_pickle=False) as z:
        index, prob = z["index"], z["prob"]
    with np.load(work / "data.npz", allow_pickle=False) as z:
        first = index[case_of[index] == case_of[index[0]]]
        x0 = z["x"][first]
    p_np = unet_probability(unet_from_bytes((work / f"unet_fold{k0}.npz").read_bytes()), x0)
    nt["max_abs_diff_vs_torch"] = float(
        np.abs(p_np - prob[np.searchsorted(index, first)].astype(np.float32)).max()
    )
    print(
        "numpy forward, 31 x 240 x 240 patient (best of 3, s): "
        + ", ".join(f"{k} {v:.3g}" for k, v in nt.items())
    )
    if forest_rows:
        print("shipped forest, its saved out-of-fold probabilities scored here:")
        print(L.summarise(forest_rows))
        print("mean of the U-Net's and the forest's probabilities:")
        print(L.summarise(mean_rows))
    if args.paired:
        other = json.loads(Path(args.paired).read_text())
        print("U-Net against the shipped model, paired:")
        print(paired_table(rows, other, "shipped learned", "U-Net"))
        if mean_rows:
            print("mean of the two against the shipped model, paired:")
            print(paired_table(mean_rows, other, "shipped learned", "mean of the two"))
            print("shipped model as scored here against its --paired rows (a check: no change):")
            print(paired_table(forest_rows, other, "--paired rows", "scored here"))
    if args.json:
        Path(args.json).write_text(json.dumps(rows, indent=1))
        if mean_rows:
            Path(args.json).with_suffix(".mean.json").write_text(json.dumps(mean_rows, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
