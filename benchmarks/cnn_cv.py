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
imports neither tumor3d nor scipy), then scores with the project's code. The
trained weights (batch norm folded) are written for the numpy forward pass
``tumor3d.learned.cnn``, which is timed here on a 31 x 240 x 240 patient.

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
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
GROUP_CODE = {"lgg": 0, "brats_flair": 1}


# ---------------------------------------------------------------- preparation (project venv)


def build_dataset(preps, folds, args) -> dict[str, np.ndarray]:
    from real_segmentation import emulate_thick

    from tumor3d.learned.cnn_data import case_input, case_target

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
            x = case_input(img, args.size, args.context)
            xs.append(x)
            ys.append(case_target(ref, args.size))
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


def _torch_unet(cin: int, base: int, levels: int):
    import torch
    import torch.nn as nn
    import torch.nn.functional as F

    class Block(nn.Sequential):
        def __init__(self, i, o):
            super().__init__(
                nn.Conv2d(i, o, 3, padding=1, bias=False),
                nn.BatchNorm2d(o),
                nn.ReLU(inplace=True),
                nn.Conv2d(o, o, 3, padding=1, bias=False),
                nn.BatchNorm2d(o),
                nn.ReLU(inplace=True),
            )

    class UNet(nn.Module):
        def __init__(self):
            super().__init__()
            ch = [base * 2**i for i in range(levels)]
            self.enc = nn.ModuleList()
            c = cin
            for o in ch:
                self.enc.append(Block(c, o))
                c = o
            self.dec = nn.ModuleList()
            for o in reversed(ch[:-1]):
                self.dec.append(Block(c + o, o))
                c = o
            self.head = nn.Conv2d(c, 1, 1)

        def forward(self, x):
            skips = []
            for i, e in enumerate(self.enc):
                x = e(x)
                if i < len(self.enc) - 1:
                    skips.append(x)
                    x = F.max_pool2d(x, 2)
            for d in self.dec:
                x = F.interpolate(x, scale_factor=2, mode="nearest")
                x = d(torch.cat([x, skips.pop()], 1))
            return self.head(x)[:, 0]

    return UNet()


def export_weights(model, path: Path, meta: dict | None = None) -> None:
    """The trained net as ``tumor3d.learned.cnn`` reads it (batch norm folded).

    ``meta`` (what it was trained on) goes in as ``meta_json``: the UTF-8 bytes
    of its JSON as a uint8 array (plain arrays only: the file never needs pickle).
    """
    out = {}
    if meta is not None:
        out["meta_json"] = np.frombuffer(json.dumps(meta, sort_keys=True).encode(), np.uint8)

    def fold(block, name):
        convs = [m for m in block if m.__class__.__name__ == "Conv2d"]
        bns = [m for m in block if m.__class__.__name__ == "BatchNorm2d"]
        for j, (c, bn) in enumerate(zip(convs, bns, strict=True)):
            s = (bn.weight / (bn.running_var + bn.eps).sqrt()).detach().numpy()
            w = c.weight.detach().numpy() * s[:, None, None, None]
            b = bn.bias.detach().numpy() - bn.running_mean.detach().numpy() * s
            out[f"{name}_{j}_w"] = w.astype(np.float32)
            out[f"{name}_{j}_b"] = b.astype(np.float32)

    for i, e in enumerate(model.enc):
        fold(e, f"enc{i}")
    for i, d in enumerate(model.dec):
        fold(d, f"dec{i}")
    out["head_w"] = model.head.weight.detach().numpy().astype(np.float32)
    out["head_b"] = model.head.bias.detach().numpy().astype(np.float32)
    np.savez(path, **out)


def train_net(x_all, y_all, tr, args, seed: int, label: str):
    """One U-Net trained on rows ``tr`` of ``x_all`` / ``y_all``: (model, slices per epoch, s)."""
    import torch
    import torch.nn.functional as F

    torch.manual_seed(seed)
    rng = np.random.default_rng(seed)
    pos = tr[y_all[tr].reshape(len(tr), -1).max(axis=1) > 0]
    neg = np.setdiff1d(tr, pos)
    model = _torch_unet(x_all.shape[1], args.base, args.levels)
    opt = torch.optim.Adam(model.parameters(), lr=args.lr, weight_decay=1e-5)
    n_neg = min(len(neg), int(round(args.neg_ratio * len(pos))))
    steps_per_epoch = int(np.ceil((len(pos) + n_neg) / args.batch))
    sched = torch.optim.lr_scheduler.OneCycleLR(
        opt, max_lr=args.lr, total_steps=args.epochs * steps_per_epoch, pct_start=0.15
    )
    t0 = time.perf_counter()
    for ep in range(args.epochs):
        model.train()
        order = rng.permutation(np.concatenate([pos, rng.choice(neg, n_neg, replace=False)]))
        tot = 0.0
        for s in range(0, len(order), args.batch):
            b = np.sort(order[s : s + args.batch])
            xb = torch.from_numpy(x_all[b].astype(np.float32))
            yb = torch.from_numpy(y_all[b].astype(np.float32))
            if rng.random() < 0.5:  # left-right flip (the image's column axis)
                xb, yb = xb.flip(-1), yb.flip(-1)
            dy, dx = rng.integers(-args.shift, args.shift + 1, 2)
            xb = torch.roll(xb, (int(dy), int(dx)), (-2, -1))
            yb = torch.roll(yb, (int(dy), int(dx)), (-2, -1))
            g = torch.from_numpy(rng.uniform(0.9, 1.1, (len(b), 1, 1, 1)).astype(np.float32))
            o = torch.from_numpy(rng.uniform(-0.1, 0.1, (len(b), 1, 1, 1)).astype(np.float32))
            xb = xb * g + o
            logit = model(xb)
            p = torch.sigmoid(logit)
            inter = (p * yb).sum()
            soft_dice = 1 - (2 * inter + 1) / (p.sum() + yb.sum() + 1)
            loss = F.binary_cross_entropy_with_logits(logit, yb) + soft_dice
            opt.zero_grad()
            loss.backward()
            opt.step()
            sched.step()
            tot += float(loss.detach()) * len(b)
        print(
            f"{label} epoch {ep + 1}/{args.epochs}: loss {tot / len(order):.4f} "
            f"({time.perf_counter() - t0:.0f} s)",
            flush=True,
        )
    return model, int(len(pos) + n_neg), time.perf_counter() - t0


def worker_final(args) -> int:
    """``--final``: one net on every row of ``data.npz`` (all folds), weights + metadata."""
    import datetime

    import torch

    torch.set_num_threads(args.threads)
    work = Path(args.work)
    with np.load(work / "data.npz", allow_pickle=False) as z:
        x_all, y_all, case_of = z["x"], z["y"], z["case"]
    meta = json.loads((work / "final_meta.json").read_text())
    t_start = datetime.datetime.now(datetime.UTC)
    load0 = os.getloadavg()
    model, per_epoch, train_s = train_net(
        x_all, y_all, np.arange(len(x_all)), args, args.seed, "final"
    )
    model.eval()
    first = np.flatnonzero(case_of == case_of[0])  # a check of the export: torch's own output
    with torch.no_grad():
        check = torch.sigmoid(model(torch.from_numpy(x_all[first].astype(np.float32)))).numpy()
    np.savez(work / "final_check.npz", index=first, prob=check)
    meta.update(
        torch_version=torch.__version__,
        trained_utc=t_start.isoformat(timespec="seconds"),
        train_wall_s=round(train_s, 1),
        load_1min_start_end=[round(load0[0], 2), round(os.getloadavg()[0], 2)],
        torch_threads=args.threads,
        seed=args.seed,
        train_slices=int(len(x_all)),
        slices_per_epoch=per_epoch,
    )
    export_weights(model, Path(args.final), meta)
    print(f"final: trained in {train_s:.0f} s, written {args.final}", flush=True)
    return 0


def worker(args) -> int:
    import torch

    if args.final:
        return worker_final(args)
    torch.set_num_threads(args.threads)
    work = Path(args.work)
    with np.load(work / "data.npz", allow_pickle=False) as z:
        d = {k: z[k] for k in z.files}
    x_all, y_all = d["x"], d["y"]
    timing = {}
    for k in args.run_folds:
        tr = np.flatnonzero(d["fold"] != k)
        held = np.flatnonzero((d["fold"] == k) & ~d["train_only"])
        model, per_epoch, train_s = train_net(x_all, y_all, tr, args, k, f"fold {k}")
        model.eval()
        t1 = time.perf_counter()
        probs = np.empty((len(held), *y_all.shape[1:]), np.float16)
        with torch.no_grad():
            for s in range(0, len(held), 32):
                b = held[s : s + 32]
                probs[s : s + len(b)] = torch.sigmoid(
                    model(torch.from_numpy(x_all[b].astype(np.float32)))
                ).numpy()
        infer_s = time.perf_counter() - t1
        np.savez(work / f"prob_fold{k}.npz", index=held, prob=probs)
        export_weights(model, work / f"unet_fold{k}.npz")
        timing[k] = {
            "train_s": train_s,
            "infer_s": infer_s,
            "held_slices": int(len(held)),
            "train_slices_per_epoch": per_epoch,
        }
        (work / f"timing_fold{k}.json").write_text(json.dumps(timing[k]))
        print(
            f"fold {k}: trained in {train_s:.0f} s, {len(held)} slices in {infer_s:.1f} s",
            flush=True,
        )
    return 0


# ---------------------------------------------------------------- scoring (project venv)


def paired_table(cnn_rows: list[dict], other_rows: list[dict], name: str, new: str) -> str:
    from scipy.stats import wilcoxon

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

            def val(r, key=key):
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
            lines.append(
                f"| {g} | {len(a)} | {label} | {a.mean():.3f} ± {a.std():.3f} ({np.median(a):.3f})"
                f" | {b.mean():.3f} ± {b.std():.3f} ({np.median(b):.3f})"
                f" | {diff.mean():+.3f} ± {diff.std():.3f} | {better} / {worse} | {pval} |"
            )
        ea = np.array([abs(o["vol_err"]) for o, _ in pairs])
        eb = np.array([abs(c["vol_err"]) for _, c in pairs])
        lines.append(
            f"| {g} | {len(pairs)} | volumes within 10 % / beyond 25 % | "
            f"{int(np.sum(ea <= 10))} / {int(np.sum(ea > 25))} | "
            f"{int(np.sum(eb <= 10))} / {int(np.sum(eb > 25))} | | | |"
        )
    return "\n".join(lines)


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


def train_final(preps, folds, args, work: Path) -> int:
    """``--final``: the dataset of every case (all folds), one torch worker, a check."""
    t0 = time.perf_counter()
    d = build_dataset(preps, folds, args)
    np.savez(work / "data.npz", **d)
    print(f"dataset {d['x'].shape} in {time.perf_counter() - t0:.0f} s", flush=True)
    groups = {g: sorted({p.spec.patient for p in preps if p.spec.group == g}) for g in args.groups}
    meta = {
        "model": "tumor3d 2-D U-Net, FLAIR (benchmarks/cnn_cv.py --final)",
        "trained_on": {
            g: {
                "cases": sum(p.spec.group == g for p in preps),
                "patients": len(groups[g]),
                "names": [p.spec.name for p in preps if p.spec.group == g],
            }
            for g in args.groups
        },
        "data": "lgg: clinical FLAIR heads at their native slices; brats_flair: BraTS 2018 "
        "FLAIR cut to 2 mm slabs every 5 mm (offsets "
        + ",".join(map(str, args.train_offsets))
        + ")",
        "settings": {
            k: getattr(args, k)
            for k in (
                "size",
                "context",
                "base",
                "levels",
                "epochs",
                "batch",
                "lr",
                "neg_ratio",
                "shift",
                "train_offsets",
            )
        },
        "input": "tumor3d.learned.cnn_data.case_input(image, size, context)",
        "loss": "BCE + soft Dice; Adam (weight decay 1e-5), one-cycle lr (15 % warm-up)",
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
    for opt in ("base", "levels", "epochs", "batch", "lr", "neg_ratio", "shift"):
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
    ap.add_argument("--seed", type=int, default=0, help="--final's seed (torch and numpy)")
    ap.add_argument("--threshold", type=float, default=0.5)
    ap.add_argument("--keep-fraction", type=float, default=1.0)
    ap.add_argument(
        "--skip-train", action="store_true", help="score the probabilities already in --work"
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

    from tumor3d.config import parse_config
    from tumor3d.learned.cnn_data import upsample
    from tumor3d.storage.manifest import data_dir

    data = data_dir()
    if not data.is_dir():
        print(f"skipped: no real data at {data} (set TUMOR3D_DATA_DIR)")
        return 0
    cfg = parse_config(Path(args.config).read_text(), source=args.config)
    specs = L.case_specs(data)
    folds = L.assign_folds(specs, args.folds)  # on every case, as learned_cv.py
    specs = [s for s in specs if s.group in args.groups]
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
            ]
            for opt in ("base", "levels", "epochs", "batch", "lr", "neg_ratio", "shift"):
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
    rows: list[dict] = []
    forest_rows: list[dict] = []  # the shipped model's saved probabilities, scored here
    mean_rows: list[dict] = []  # the mean of the two probabilities (fixed equal weights)
    timing = {}

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

    for k in run_folds:
        with np.load(work / f"prob_fold{k}.npz", allow_pickle=False) as z:
            index, prob = z["index"], z["prob"]
        timing[k] = json.loads((work / f"timing_fold{k}.json").read_text())
        for ci, p in enumerate(preps):
            if folds[p.spec.patient] != k:
                continue
            sel = index[case_of[index] == ci]
            assert not train_only[sel].any() and len(sel) == p.image.shape[0]
            pr = upsample(prob[np.searchsorted(index, sel)], p.image.shape)
            scored(p, pr, k, rows, "U-Net")
            if args.forest_prob:
                f = Path(args.forest_prob) / (p.spec.name.replace("/", "__") + ".npz")
                with np.load(f, allow_pickle=False) as z:
                    pf = z[args.forest_key].astype(np.float32)
                scored(p, pf, k, forest_rows, "forest")
                scored(p, 0.5 * (pr + pf), k, mean_rows, "mean")
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
